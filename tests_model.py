"""Tests of model.py and train.py: causality, shapes, schedule, over-fitting, checkpoints, scripts.

    python -m pytest tests_model.py -q
"""
import dataclasses
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import env
import model
import train

HERE = os.path.dirname(os.path.abspath(__file__))
TINY = dict(d_vis=16, d_state=16, d_model=32, n_layer=2, n_head=2, dropout=0.0)  # fast test network


# --- helpers ---

@pytest.fixture(autouse=True)
def one_thread():
    """Tiny networks run fastest on one thread, and on a busy 2-core machine two OpenMP threads
    stall each other (a few ms per op)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def write_demos(path, n_episodes=4, steps=(40, 70), size=16, seed=0, env_config=None):
    """A tiny synthetic dataset in collect.py's format: ep_XXXXXX.npz + meta.json."""
    rng = np.random.default_rng(seed)
    os.makedirs(path, exist_ok=True)
    for i in range(n_episodes):
        T = int(rng.integers(*steps))
        action = rng.uniform(-1, 1, (T, env.ACTION_DIM)).astype(np.float32)
        action[:, env.GRIP] = rng.integers(-1, 2, T)
        np.savez_compressed(
            os.path.join(path, f"ep_{i:06d}.npz"),
            depth=rng.integers(0, 256, (T, size, size), dtype=np.uint8),
            state=rng.standard_normal((T, env.STATE_DIM)).astype(np.float32), action=action,
            skill=np.sort(rng.integers(0, len(env.SKILLS), T)).astype(np.int8),
            receptacle=np.full(T, rng.integers(0, len(env.RECEPTACLES) + 1), np.int8),
            reward=rng.normal(0.1, 0.5, T).astype(np.float32),
            success=np.bool_(rng.random() < 0.8), layout=np.int64(i % 3), difficulty=np.str_("easy"),
            seed=np.int64(i), index=np.int64(i))
    meta = {"env_config": env_config or {"depth_size": size, "max_steps": 500},
            "state_layout": [list(x) for x in env.STATE_LAYOUT], "skills": list(env.SKILLS),
            "receptacles": list(env.RECEPTACLES)}
    with open(os.path.join(path, "meta.json"), "w") as f:
        json.dump(meta, f)
    return path


def random_batch(cfg, B=2, T=None, seed=0):
    g = torch.Generator().manual_seed(seed)
    T = T or cfg.context
    S = cfg.depth_size
    action = torch.rand(B, T, env.ACTION_DIM, generator=g) * 2 - 1
    action[..., env.GRIP] = torch.randint(-1, 2, (B, T), generator=g).float()
    return {"depth": torch.rand(B, T, 1, S, S, generator=g), "state": torch.randn(B, T, env.STATE_DIM, generator=g),
            "prev_action": torch.rand(B, T, env.ACTION_DIM, generator=g) * 2 - 1, "action": action,
            "skill": torch.randint(0, cfg.n_skills, (B, T), generator=g),
            "receptacle": torch.randint(0, cfg.n_receptacles, (B, T), generator=g),
            "rtg": torch.randn(B, T, generator=g), "mask": torch.ones(B, T, dtype=torch.bool)}


def fake_obs(rng, size):
    obs = {"depth": rng.random((size, size, 1), dtype=np.float32)}
    for k, n in env.STATE_LAYOUT:
        obs[k] = rng.standard_normal(n).astype(np.float32)
    return obs


def run_script(args, timeout=120):
    r = subprocess.run(args, cwd=HERE, capture_output=True, text=True, timeout=timeout,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r.stdout


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """`python train.py` for 2 epochs on a tiny dataset -> (data dir, checkpoint path, stdout)."""
    root = tmp_path_factory.mktemp("train")
    data = write_demos(str(root / "demos"))
    out = str(root / "ckpt" / "st.pt")
    stdout = run_script([sys.executable, "train.py", "--data", data, "--out", out, "--epochs", "2",
                         "--warmup-epochs", "1", "--batch-size", "4", "--d-model", "32", "--n-head", "2",
                         "--context", "8", "--log-interval", "1", "--seed", "1", "--threads", "1"])
    return data, out, stdout


# --- model ---

@pytest.mark.parametrize("variant", model.VARIANTS)
def test_output_shapes(variant):
    cfg = model.ModelConfig(depth_size=16, context=6, variant=variant, **TINY)
    out = model.SkillTransformer(cfg)(random_batch(cfg, B=3))
    assert out["arm"].shape == (3, 6, 7) and out["base"].shape == (3, 6, 2) and out["grip_logits"].shape == (3, 6, 3)
    assert ("skill_logits" in out) == (variant in ("st", "lstm", "dt_skill"))
    if "skill_logits" in out:
        assert out["skill_logits"].shape == (3, 6, 5)
    if variant in ("st", "lstm"):
        assert out["aux_logits"].shape == (3, 6, 4)


@pytest.mark.parametrize("variant", model.VARIANTS)
def test_causality(variant):
    """Changing step k's inputs (any of them) never changes an output at a step < k."""
    cfg = model.ModelConfig(depth_size=16, context=7, variant=variant, **TINY)
    net = model.SkillTransformer(cfg).eval()
    base = random_batch(cfg, B=2, seed=1)
    other = random_batch(cfg, B=2, seed=2)
    with torch.no_grad():
        ref = net(base)
        for k in (0, 3, 6):
            for key in ("depth", "state", "prev_action", "skill", "rtg"):
                pert = dict(base)
                pert[key] = base[key].clone()
                pert[key][:, k:] = other[key][:, k:]
                out = net(pert)
                for name in ref:  # skill/aux logits (skill inference), arm/base/grip (action inference)
                    assert torch.allclose(ref[name][:, :k], out[name][:, :k], atol=1e-5), (variant, key, k, name)
            pert = {**base, "depth": other["depth"]}
            assert not torch.allclose(ref["arm"][:, k:], net(pert)["arm"][:, k:])  # the future does change


def test_padding_matches_rollout():
    """A left-padded training window gives the Policy's outputs on the same steps."""
    cfg = model.ModelConfig(depth_size=16, context=5, **TINY)
    net = model.SkillTransformer(cfg).eval()
    policy = model.Policy(net, {"depth_size": 16}, rtg_max=1.0)
    rng = np.random.default_rng(0)
    obs = [fake_obs(rng, 16) for _ in range(3)]
    actions = [policy.act(o) for o in obs]
    C = cfg.context
    depth = torch.zeros(1, C, 1, 16, 16)
    state = torch.zeros(1, C, env.STATE_DIM)
    prev = torch.zeros(1, C, env.ACTION_DIM)
    skill = torch.zeros(1, C, dtype=torch.long)
    for i, o in enumerate(obs):
        depth[0, C - 3 + i, 0] = torch.from_numpy(env.depth_to_uint8(o["depth"])).float() / 255
        state[0, C - 3 + i] = torch.from_numpy(env.state_vector(o))
        skill[0, C - 3 + i] = actions[i][1]
        if i:
            prev[0, C - 3 + i] = torch.from_numpy(actions[i - 1][0])
    mask = torch.tensor([[False] * (C - 3) + [True] * 3])
    with torch.no_grad():
        out = net({"depth": depth, "state": state, "prev_action": prev, "skill": skill, "mask": mask})
    assert int(out["skill_logits"][0, -1].argmax()) == actions[-1][1]
    np.testing.assert_allclose(out["arm"][0, -1].clamp(-1, 1).numpy(), actions[-1][0][:7], atol=1e-5)


def test_focal_loss_matches_cross_entropy_at_gamma_0():
    logits, target = torch.randn(10, 5), torch.randint(0, 5, (10,))
    torch.testing.assert_close(model.focal_loss(logits, target, gamma=0.0).mean(),
                               torch.nn.functional.cross_entropy(logits, target))
    assert (model.focal_loss(logits, target) <= model.focal_loss(logits, target, gamma=0.0)).all()


def test_overfit_tiny_batch():
    torch.manual_seed(0)
    cfg = model.ModelConfig(depth_size=16, context=8, **TINY)
    net = model.SkillTransformer(cfg)
    batch = random_batch(cfg, B=4)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    first = None
    for _ in range(200):
        loss = net.compute_loss(net(batch), batch)["loss"]
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.1 * first, (first, loss.item())


@pytest.mark.parametrize("variant", model.VARIANTS)
def test_every_variant_trains_one_step(variant):
    cfg = model.ModelConfig(depth_size=16, context=6, variant=variant, **TINY)
    net = model.SkillTransformer(cfg)
    batch = random_batch(cfg)
    batch["mask"][0, :3] = False  # left padding
    losses = net.compute_loss(net(batch), batch)
    assert set(losses) >= {"loss", "arm", "base", "grip"} and torch.isfinite(losses["loss"])
    assert ("skill" in losses) == (variant in ("st", "lstm", "dt_skill"))
    assert ("aux" in losses) == (variant in ("st", "lstm"))
    before = [p.detach().clone() for p in net.parameters()]
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3)
    losses["loss"].backward()
    opt.step()
    assert all(p.grad is not None for p in net.parameters())  # every parameter is used (DDP needs it)
    assert any(not torch.equal(a, b) for a, b in zip(before, net.parameters()))


def test_resnet18_encoder():
    cfg = model.ModelConfig(depth_size=32, context=2, encoder="resnet18", **TINY)
    net = model.SkillTransformer(cfg)
    assert 10e6 < net.num_params() < 13e6
    assert net(random_batch(cfg, B=1))["arm"].shape == (1, 2, 7)


# --- train.py ---

def test_lr_schedule():
    cfg = train.TrainConfig(epochs=50, warmup_epochs=5, lr=5e-4, lr_start=1e-8)
    assert train.get_lr(0, cfg) == pytest.approx(1e-8)
    assert train.get_lr(2.5, cfg) == pytest.approx((1e-8 + 5e-4) / 2)
    assert train.get_lr(5, cfg) == pytest.approx(5e-4)
    assert train.get_lr(27.5, cfg) == pytest.approx(2.5e-4)
    assert train.get_lr(50, cfg) == pytest.approx(0.0, abs=1e-12)
    lrs = [train.get_lr(e / 10, cfg) for e in range(501)]
    assert np.argmax(lrs) == 50 and all(a >= b for a, b in zip(lrs[50:], lrs[51:]))


def test_windows_and_padding(tmp_path):
    demos, meta = train.load_demos(write_demos(str(tmp_path / "d")))
    cfg = train.TrainConfig(context=8, batch_size=4)
    w = train.epoch_windows(demos, cfg, epoch=0)
    assert len(w) % 4 == 0 and np.array_equal(w, train.epoch_windows(demos, cfg, epoch=0))
    batch = train.get_batch(demos, np.array([[0, 2], [1, 30]]), 8, "cpu")
    assert batch["depth"].shape == (2, 8, 1, 16, 16) and batch["depth"].max() <= 1
    assert batch["mask"][0].tolist() == [False] * 5 + [True] * 3 and batch["mask"][1].all()
    np.testing.assert_array_equal(batch["state"][1, -1].numpy(), demos[1]["state"][30])
    np.testing.assert_array_equal(batch["prev_action"][1, -1].numpy(), demos[1]["action"][29])
    assert batch["prev_action"][0, 5].abs().sum() == 0  # a_{-1} = 0 at the episode start
    assert batch["rtg"][1, -1] == pytest.approx(demos[1]["reward"][30:].sum(), rel=1e-5)


def test_bad_data_is_refused(tmp_path):
    data = write_demos(str(tmp_path / "d"), n_episodes=2)
    with open(os.path.join(data, "ep_000001.npz"), "wb") as f:
        f.write(b"not a zip")
    with pytest.raises(ValueError, match="ep_000001.npz"):
        train.load_demos(data)
    data2 = write_demos(str(tmp_path / "d2"), n_episodes=1)
    z = dict(np.load(os.path.join(data2, "ep_000000.npz")))
    z["state"] = z["state"][:, :20]
    np.savez(os.path.join(data2, "ep_000000.npz"), **z)
    with pytest.raises(ValueError, match="state has shape"):
        train.load_demos(data2)


def test_train_script_then_policy(trained):
    data, out, stdout = trained
    assert "samples/s" in stdout and "eta" in stdout
    for path in (out, out[:-3] + ".last.pt", out[:-3] + ".csv"):
        assert os.path.exists(path), path
    ckpt = torch.load(out, weights_only=True)
    assert ckpt["epoch"] == 2 and ckpt["config"]["variant"] == "st" and ckpt["env_config"]["depth_size"] == 16
    policy = model.load_policy(out)
    assert policy.variant == "st" and policy.env_config == ckpt["env_config"]
    rng = np.random.default_rng(0)
    for t in range(12):  # more steps than the context (8): the window slides
        action, skill = policy.act(fake_obs(rng, 16), reward=0.1)
        assert action.shape == (10,) and action.dtype == np.float32 and 0 <= skill < 5
        assert np.all(np.abs(action) <= 1) and action[env.GRIP] in env.GRIP_VALUES
    policy.reset()
    assert policy.t == 0 and not policy.mask.any()


def test_checkpoint_round_trip(tmp_path):
    cfg = model.ModelConfig(depth_size=16, context=4, variant="dt_skill", **TINY)
    net = model.SkillTransformer(cfg).eval()
    path = str(tmp_path / "c.pt")
    train.save_atomic({"model": net.state_dict(), "model_args": dataclasses.asdict(cfg),
                       "env_config": {"depth_size": 16}, "rtg_max": 3.0}, path)
    policy = model.load_policy(path)
    batch = random_batch(cfg, B=1)
    with torch.no_grad():
        a, b = net(batch), policy.model(batch)
    for k in a:
        torch.testing.assert_close(a[k], b[k])
    assert policy.rtg_max == 3.0 and policy.variant == "dt_skill"
    with pytest.raises(FileNotFoundError):
        model.load_policy(str(tmp_path / "missing.pt"))
    torch.save({"weights": 1}, str(tmp_path / "other.pt"))
    with pytest.raises(ValueError, match="not a Skill Transformer checkpoint"):
        model.load_policy(str(tmp_path / "other.pt"))
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(ValueError, match="not a readable"):
        model.load_policy(str(tmp_path / "junk.pt"))


def test_env_config_mismatch_is_refused(trained, tmp_path):
    data, out, _ = trained
    other = write_demos(str(tmp_path / "other"), env_config={"depth_size": 16, "max_steps": 999})
    for name in ("st.pt", "st.last.pt", "st.csv"):
        shutil.copy(os.path.join(os.path.dirname(out), name), tmp_path / name)
    cfg = train.TrainConfig(data=other, out=str(tmp_path / "st.pt"), resume=True, epochs=3, batch_size=4,
                            d_model=32, n_head=2, context=8, threads=1)
    with pytest.raises(ValueError, match="env_config"):
        train.train(cfg)
    cfg.resume, cfg.init = False, out
    with pytest.raises(ValueError, match="max_steps"):
        train.train(cfg)


def test_resume_continues(trained, tmp_path):
    data, out, _ = trained
    for name in ("st.pt", "st.last.pt", "st.csv"):
        shutil.copy(os.path.join(os.path.dirname(out), name), tmp_path / name)
    cfg = train.TrainConfig(data=data, out=str(tmp_path / "st.pt"), resume=True, epochs=3, warmup_epochs=1,
                            batch_size=4, d_model=32, n_head=2, context=8, log_interval=1, seed=1, threads=1)
    train.train(cfg)
    assert torch.load(str(tmp_path / "st.last.pt"), weights_only=True)["epoch"] == 3


def test_torchrun_two_processes(tmp_path):
    data = write_demos(str(tmp_path / "d"), n_episodes=2, steps=(20, 25))
    out = str(tmp_path / "ddp.pt")
    stdout = run_script([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "train.py",
                         "--data", data, "--out", out, "--epochs", "2", "--batch-size", "4", "--d-model", "32",
                         "--n-head", "2", "--context", "8", "--log-interval", "1"])
    assert "world 2" in stdout and stdout.count("samples/s") == 2  # 2 epochs x 1 iteration, rank 0 only
    assert model.load_policy(out).variant == "st"
