"""Tests of collect.py and evaluate.py on the real simulator and expert, with tiny sizes.

    python -m pytest tests_collect_eval.py -q
"""
import dataclasses
import itertools
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import collect
import env
import evaluate
import expert
import model

HERE = os.path.dirname(os.path.abspath(__file__))
DEPTH = 16   # smallest sensible camera: the tests check the plumbing, not the pictures


def run(script, *args, check=True):
    """Run a stage as a subprocess (as a user would) -> CompletedProcess with text output."""
    p = subprocess.run([sys.executable, os.path.join(HERE, script), *map(str, args)],
                       capture_output=True, text=True, timeout=600, cwd=HERE)
    if check and p.returncode != 0:
        raise AssertionError(f"{script} {args} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def collect_run(out, episodes, *extra, check=True):
    return run("collect.py", "--episodes", episodes, "--out", out, "--depth-size", DEPTH, "--seed", 0,
               "--log-every", 0, *extra, check=check)


def read_dir(out):
    """{file name: {key: array}} of every episode file in a dataset directory."""
    return {n: collect.load_episode(os.path.join(out, n)) for n in sorted(os.listdir(out)) if n.endswith(".npz")}


def assert_same(a, b):
    assert sorted(a) == sorted(b)
    for name in a:
        assert sorted(a[name]) == sorted(b[name]), name
        for key in a[name]:
            assert a[name][key].dtype == b[name][key].dtype and np.array_equal(a[name][key], b[name][key]), (name, key)


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    """Three successful demonstrations written by one worker; the reference for the other tests.
    (Train episodes 2 and 3 fail at the time of writing, so the skipping of failures is exercised.)"""
    out = tmp_path_factory.mktemp("demos") / "a"
    collect_run(out, 3, "--workers", 1)
    return out


# --- collect.py ---

def test_collect_round_trip(demos):
    names = sorted(n for n in os.listdir(demos) if n.endswith(".npz"))
    assert len(names) == 3 and all(re.fullmatch(r"ep_\d{6}\.npz", n) for n in names)
    assert not [n for n in os.listdir(demos) if n.endswith(".tmp")]
    for name in names:
        with np.load(demos / name, allow_pickle=False) as f:
            d = {k: f[k] for k in f.files}
        T = len(d["action"])
        assert T > 10
        shapes = {"depth": ((T, DEPTH, DEPTH), np.uint8), "state": ((T, env.STATE_DIM), np.float32),
                  "action": ((T, env.ACTION_DIM), np.float32), "skill": ((T,), np.int8),
                  "receptacle": ((T,), np.int8), "reward": ((T,), np.float32),
                  "success": ((), np.bool_), "layout": ((), np.int64), "seed": ((), np.int64),
                  "index": ((), np.int64)}
        for key, (shape, dtype) in shapes.items():
            assert d[key].shape == shape and d[key].dtype == dtype, (key, d[key].shape, d[key].dtype)
        assert d["difficulty"].shape == () and str(d["difficulty"]) in env.DIFFICULTIES
        assert bool(d["success"])                                  # default: successful demos only
        assert int(d["index"]) == int(name[3:9])
        ep = env.make_episodes("train", int(d["index"]) + 1, seed=0)[int(d["index"])]
        assert int(d["layout"]) == ep.layout and str(d["difficulty"]) == ep.difficulty
        assert int(d["seed"]) == collect.reset_seed(0, int(d["index"]))
        assert set(np.unique(d["skill"])) <= set(range(len(env.SKILLS))) and len(np.unique(d["skill"])) >= 3
        assert np.all(np.abs(d["action"][:, :9]) <= 1.0 + 1e-6)
        assert set(np.unique(d["action"][:, 9])) <= set(env.GRIP_VALUES)
        collect.load_episode(demos / name)
    meta = json.loads((demos / "meta.json").read_text())
    assert meta["env_config"]["depth_size"] == DEPTH and meta["seed"] == 0 and meta["noise"] == 0.0
    assert meta["skills"] == list(env.SKILLS) and meta["state_layout"][0] == ["joint", 7]
    assert {"python", "numpy", "mujoco"} <= set(meta["versions"])
    stats = run("collect.py", "--stats", demos).stdout
    assert "3 episodes" in stats and "success 100.0%" in stats and "navigate" in stats


def test_collect_same_with_two_workers(demos, tmp_path):
    collect_run(tmp_path / "b", 3, "--workers", 2)
    assert_same(read_dir(demos), read_dir(tmp_path / "b"))


def test_collect_resume(demos, tmp_path):
    out = tmp_path / "c"
    collect_run(out, 1, "--workers", 1)                            # "killed" after one episode
    collect_run(out, 3, "--workers", 2)                            # resumed with the full count
    assert_same(read_dir(demos), read_dir(out))
    last = sorted(n for n in os.listdir(out) if n.endswith(".npz"))[-1]
    os.remove(out / last)                                          # killed while writing that one:
    (out / (last + ".4242.tmp")).write_bytes(b"half a zip")        # only its temporary file is there
    collect_run(out, 3, "--workers", 1)
    assert_same(read_dir(demos), read_dir(out))
    assert sorted(os.listdir(out)) == sorted(os.listdir(demos))    # no temporary file left


def test_collect_refuses_corrupt_foreign_and_mismatched(demos, tmp_path):
    out = tmp_path / "d"
    shutil.copytree(demos, out)
    (out / "ep_000077.npz").write_bytes(b"not a zip file")
    p = collect_run(out, 2, check=False)
    assert p.returncode != 0 and "ep_000077.npz" in p.stderr and "not a readable" in p.stderr
    os.remove(out / "ep_000077.npz")
    np.savez(out / "ep_000078.npz", x=np.zeros(3))                 # a valid zip of the wrong content
    p = collect_run(out, 2, check=False)
    assert p.returncode != 0 and "ep_000078.npz" in p.stderr and "missing keys" in p.stderr
    os.remove(out / "ep_000078.npz")
    np.savez(out / "notes.npz", x=np.zeros(3))
    p = collect_run(out, 2, check=False)
    assert p.returncode != 0 and "notes.npz" in p.stderr and "foreign" in p.stderr
    os.remove(out / "notes.npz")
    p = collect_run(out, 2, "--seed", 1, check=False)
    assert p.returncode != 0 and "meta.json" in p.stderr and "seed" in p.stderr
    p = run("collect.py", "--episodes", 2, "--out", out, "--depth-size", 24, check=False)
    assert p.returncode != 0 and "env_config" in p.stderr
    with pytest.raises(ValueError, match="ep_000000.npz"):
        bad = dict(collect.load_episode(out / "ep_000000.npz"), reward=np.full(3, np.nan, np.float32))
        np.savez(tmp_path / "ep_000000.npz", **bad)
        collect.load_episode(tmp_path / "ep_000000.npz")


def test_collect_keep_failed_shards_and_give_up(tmp_path):
    short = ("--max-steps", 20, "--workers", 1)                     # too short for the expert to succeed
    collect_run(tmp_path / "all", 3, "--keep-failed", *short)
    whole = read_dir(tmp_path / "all")
    assert sorted(whole) == ["ep_000000.npz", "ep_000001.npz", "ep_000002.npz"]
    assert not any(bool(d["success"]) for d in whole.values()) and all(len(d["action"]) == 20 for d in whole.values())
    for shard in ("0/2", "1/2"):                                    # two machines, one directory
        collect_run(tmp_path / "sharded", 3, "--keep-failed", "--shard", shard, *short)
    assert_same(whole, read_dir(tmp_path / "sharded"))
    p = collect_run(tmp_path / "none", 1, "--max-draws", 2, *short, check=False)
    assert p.returncode != 0 and "only 0/1 demonstrations after 2" in p.stderr
    assert not [n for n in os.listdir(tmp_path / "none") if n != "meta.json"]


# --- evaluate.py ---

def parse_markdown_table(md, title_start):
    """The table under the heading that starts with title_start -> (header, rows)."""
    lines = md[md.index("## " + title_start):].splitlines()[2:]
    table = list(itertools.takewhile(lambda line: line.startswith("|"), lines))
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in table]
    return rows[0], rows[2:]


def test_evaluate_table1_experts(tmp_path):
    out = tmp_path / "eval.json"
    p = run("evaluate.py", "--policy", "expert:oracle", "--policy", "expert:fixed", "--split", "both",
            "--episodes", 4, "--workers", 2, "--depth-size", DEPTH, "--out", out, "--log-every", 0)
    assert "Table 1" in p.stdout and "eta" in p.stdout
    md = (tmp_path / "eval.md").read_text()
    res = json.loads(out.read_text())
    header, rows = parse_markdown_table(md, "Table 1")
    assert header == ["Method"] + [f"{s} {g}" for s in ("Seen", "Unseen") for g in ("All", "Easy", "Hard", "Very Hard")]
    assert [r[0] for r in rows] == ["expert:oracle", "expert:fixed"]
    for m, row in zip(res["methods"], rows):                         # the table shows the JSON numbers
        want = [evaluate.fmt(m["results"][s]["no_perturb"][f"success_{g}"])
                for s in ("seen", "unseen") for g in ("all", "easy", "hard", "very_hard")]
        assert row[1:] == want
    assert len(res["rollouts"]) == 2 * 2 * 4
    oracle, fixed = (m["results"]["unseen"]["no_perturb"] for m in res["methods"])
    assert oracle["success_all"]["mean"] >= fixed["success_all"]["mean"]
    assert fixed["success_hard"]["mean"] == 0.0 == fixed["success_very_hard"]["mean"]
    assert sum(oracle["failures"].values()) == 4 and "Details: unseen" in md


def test_evaluate_table2_perturb(tmp_path):
    out = tmp_path / "p.json"
    p = run("evaluate.py", "--policy", "expert:oracle", "--policy", "expert:fixed", "--perturb", "--episodes", 1,
            "--workers", 2, "--depth-size", DEPTH, "--out", out, "--video", tmp_path / "video", "--video-episodes", 1)
    folders = sorted(os.listdir(tmp_path / "video"))                  # RGB with OpenGL, else depth frames
    assert len(folders) == 2 and "video:" in p.stdout
    frames = sorted(os.listdir(tmp_path / "video" / folders[0]))
    assert len(frames) > 10 and (tmp_path / "video" / folders[0] / frames[0]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = (tmp_path / "p.md").read_text()
    header, rows = parse_markdown_table(md, "Table 2")
    assert header == ["Method", "Pick No Perturb", "Pick Perturb", "Skill Acc No Perturb", "Skill Acc Perturb"]
    res = json.loads(out.read_text())
    assert [r[0] for r in rows] == ["expert:oracle", "expert:fixed"]
    for m, row in zip(res["methods"], rows):
        r = m["results"]["unseen"]
        assert row[1:] == [evaluate.fmt(r[c][k]) for k in ("picked", "skill_accuracy") for c in evaluate.CONDITIONS]
    episodes = env.make_episodes("unseen", max(r["index"] for r in res["rollouts"]) + 1)
    assert all(evaluate.target_in_drawer(episodes[r["index"]]) for r in res["rollouts"])
    fixed = res["methods"][1]["results"]["unseen"]["no_perturb"]
    assert fixed["picked"]["mean"] == 0.0                              # it never opens the drawer


def test_fixed_plan_fails_where_oracle_succeeds():
    """On a target in a closed receptacle the fixed plan (M3) cannot pick; the oracle plan can."""
    e = env.RearrangeEnv(depth_size=DEPTH)
    hard = [ep for ep in env.make_episodes("unseen", 24) if ep.kind == "object_closed"][:4]
    for ep in hard:
        seed = evaluate.reset_seed("unseen", ep.index, 0)
        fixed = evaluate.rollout(expert.Expert(e, plan="fixed"), e, ep, seed)
        assert not fixed["success"] and not fixed["picked"], ep
        if evaluate.rollout(expert.Expert(e, plan="oracle"), e, ep, seed)["success"]:
            break
    else:
        pytest.fail(f"the oracle expert failed all of {[ep.index for ep in hard]}")


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Two untrained tiny Skill Transformers ("training seeds") in the format model.load_policy reads."""
    root = tmp_path_factory.mktemp("ckpt")
    env_config = dataclasses.asdict(env.EnvConfig(depth_size=DEPTH, max_steps=25))
    paths = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        cfg = model.ModelConfig(depth_size=DEPTH, context=4, d_vis=16, d_state=16, d_model=32, n_head=2)
        path = str(root / f"st_s{seed}.pt")
        torch.save({"model": model.SkillTransformer(cfg).state_dict(), "model_args": dataclasses.asdict(cfg),
                    "env_config": env_config, "rtg_max": 0.0}, path)
        paths.append(path)
    return paths


def test_evaluate_checkpoints(checkpoints, tmp_path):
    out = tmp_path / "ck.json"
    run("evaluate.py", "--policy", ",".join(checkpoints), "--policy", checkpoints[0], "--seeds", 2,
        "--episodes", 2, "--workers", 2, "--out", out)
    res = json.loads(out.read_text())
    header, rows = parse_markdown_table((tmp_path / "ck.md").read_text(), "Table 1")
    assert header == ["Method", "All", "Easy", "Hard", "Very Hard"]
    assert [r[0] for r in rows] == [f"st ({','.join(checkpoints)})", f"st ({checkpoints[0]})"]
    joined, single = (m["results"]["unseen"]["no_perturb"] for m in res["methods"])
    assert len(joined["units"]) == 4 and len(single["units"]) == 2 and len(res["rollouts"]) == 12
    assert all(r["steps"] <= 25 for r in res["rollouts"])                # the checkpoint's env config
    assert {r["failure"] for r in res["rollouts"]} <= {"timeout", "collision", "collision_accum"}
    assert 0 <= joined["skill_accuracy"]["mean"] <= 100
    rate = evaluate.success_check(checkpoints[0], 2)
    assert isinstance(rate, float) and rate == 0.0                        # untrained: no success in 25 steps


def test_evaluate_checkpoint_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.pt"):
        evaluate.load_checkpoint(str(tmp_path / "nothere.pt"))
    bad = tmp_path / "foreign.pt"
    bad.write_bytes(b"certainly not a checkpoint")
    with pytest.raises(ValueError, match="foreign.pt"):
        evaluate.load_checkpoint(str(bad))
    p = run("evaluate.py", "--policy", bad, "--episodes", 1, "--workers", 1, "--out", tmp_path / "x.json", check=False)
    assert p.returncode != 0 and "foreign.pt" in p.stderr and "Traceback" not in p.stderr
    p = run("evaluate.py", "--policy", tmp_path / "gone.pt", "--episodes", 1, check=False)
    assert p.returncode != 0 and "gone.pt" in p.stderr and "not found" in p.stderr


def test_spread_over_training_or_rollout_seeds():
    units = [{"member": "a", "seed": 0, "x": 10.0}, {"member": "a", "seed": 1, "x": 30.0}]
    assert evaluate.spread(units, "x") == {"mean": 20.0, "std": 10.0}             # rollout seeds
    units += [{"member": "b", "seed": 0, "x": 40.0}, {"member": "b", "seed": 1, "x": 40.0}]
    assert evaluate.spread(units, "x") == {"mean": 30.0, "std": 10.0}             # training seeds
    assert evaluate.spread(units + [{"member": "c", "seed": 0, "x": None}], "x") is None


def test_help():
    for script in ("collect.py", "evaluate.py"):
        p = run(script, "--help")
        assert "python " + script in p.stdout and "--episodes" in p.stdout
