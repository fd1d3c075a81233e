"""env.py and expert.py tests (merged into test_all.py)."""
import numpy as np
import pytest

import env
import expert


# --- env.py ---

def _random_action(rng):
    return np.concatenate([rng.uniform(-1, 1, 9), [rng.choice(env.GRIP_VALUES)]]).astype(np.float32)


def test_observation_shapes_and_dtypes():
    e = env.RearrangeEnv(depth_size=16)
    obs, info = e.reset(seed=0, options={"episode": env.make_episodes("train", 1)[0]})
    assert obs["depth"].shape == (16, 16, 1) and obs["depth"].dtype == np.float32
    assert 0.0 <= obs["depth"].min() and obs["depth"].max() <= 1.0
    for key, n in env.STATE_LAYOUT:
        assert obs[key].shape == (n,) and obs[key].dtype == np.float32, key
    assert env.state_vector(obs).shape == (env.STATE_DIM,)
    assert env.depth_to_uint8(obs["depth"]).dtype == np.uint8
    assert info["skill_gt"] in range(len(env.SKILLS)) and info["receptacle"] in range(len(env.RECEPTACLES) + 1)


def test_determinism_same_seed_same_bytes():
    ep = env.make_episodes("seen", 3)[2]
    runs = []
    for _ in range(2):
        e, rng = env.RearrangeEnv(depth_size=16), np.random.default_rng(7)
        obs, _ = e.reset(seed=5, options={"episode": ep})
        for _ in range(100):
            obs, *_ = e.step(_random_action(rng))
        runs.append(b"".join(np.ascontiguousarray(v).tobytes() for v in obs.values()))
    assert runs[0] == runs[1]


def test_reward_terms_sum_to_reward():
    e, rng = env.RearrangeEnv(depth_size=8), np.random.default_rng(0)
    e.reset(seed=0, options={"episode": env.make_episodes("train", 2)[1]})
    for _ in range(150):
        _, reward, term, trunc, info = e.step(_random_action(rng))
        assert reward == pytest.approx(sum(info["reward_terms"].values()), abs=1e-9)
        if term or trunc:
            break


def test_every_layout_compiles_and_is_navigable():
    assert not set(env.TRAIN_LAYOUTS) & set(env.EVAL_LAYOUTS)
    assert len(env.TRAIN_LAYOUTS) == 60 and len(env.EVAL_LAYOUTS) == 20
    for lid in env.TRAIN_LAYOUTS + env.EVAL_LAYOUTS:
        layout = env.make_layout(lid)
        assert env._navigable(layout), lid
    for lid in (0, 1000):                 # compiling all 80 takes a while: two suffice with the check above
        env.build_spec(env.make_layout(lid)).compile()


def test_episode_mix_and_determinism():
    eps = env.make_episodes("unseen", 400, seed=0)
    kinds = [ep.kind for ep in eps]
    assert {k: kinds.count(k) for k in env.KINDS} == {"easy": 100, "object_closed": 100, "goal_closed": 100, "very_hard": 100}
    assert all(ep.layout in env.EVAL_LAYOUTS for ep in eps)
    assert env.make_episodes("unseen", 5, seed=0) == eps[:5]          # episode i does not depend on n
    train, seen = env.make_episodes("train", 50), env.make_episodes("seen", 50)
    assert all(ep.layout in env.TRAIN_LAYOUTS for ep in train + seen)
    assert not {ep.robot_start for ep in train} & {ep.robot_start for ep in seen}
    for ep in eps[:40]:
        assert (ep.obj_receptacle > 0) == (ep.kind in ("object_closed", "very_hard"))
        assert (ep.goal_receptacle > 0) == (ep.kind in ("goal_closed", "very_hard"))


def test_bad_inputs_raise_clear_errors():
    e = env.RearrangeEnv(depth_size=8)
    e.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        e.step(np.zeros(9))
    with pytest.raises(ValueError, match="finite"):
        e.step(np.array([np.nan] + [0.0] * 9))
    with pytest.raises(ValueError, match="grip"):
        e.step(np.array([0.0] * 9 + [0.5]))
    with pytest.raises(ValueError, match="split"):
        env.make_episodes("test", 1)
    with pytest.raises(ValueError, match="layout"):
        env.make_layout(77)
    with pytest.raises(ValueError, match="unknown env option"):
        env.RearrangeEnv(depth=3)
    e2 = env.RearrangeEnv(depth_size=8, max_steps=2)
    e2.reset(seed=0)
    e2.step(np.zeros(10)); e2.step(np.zeros(10))
    with pytest.raises(RuntimeError, match="reset"):
        e2.step(np.zeros(10))


def test_random_actions_fuzz():
    """Random actions over many layouts: no NaN, no MuJoCo warning, objects above the floor,
    robot inside the walls."""
    e, rng = env.RearrangeEnv(depth_size=8), np.random.default_rng(1)
    for ep in env.make_episodes("train", 6, seed=3):
        obs, _ = e.reset(seed=ep.index, options={"episode": ep})
        for _ in range(200):
            obs, reward, term, trunc, info = e.step(_random_action(rng))
            assert np.isfinite(reward) and all(np.all(np.isfinite(v)) for v in obs.values())
            if term or trunc:
                break
        p = e.privileged()
        assert all(w.number == 0 for w in e.data.warning)
        assert (p["objects"][:, 2] > 0).all()
        W, D = e.layout.room
        assert 0 < p["base"][0] < W and 0 < p["base"][1] < D


# --- expert.py ---

def _run_expert(ep, plan="oracle", seed=0):
    e = env.RearrangeEnv(depth_size=8)
    x = expert.Expert(e, plan=plan, seed=seed)
    obs, info = e.reset(seed=seed, options={"episode": ep})
    x.reset()
    actions, skills = [], []
    while True:
        a, z = x.act(obs)
        actions.append(a); skills.append(z)
        obs, _, term, trunc, info = e.step(a)
        if term or trunc:
            return info, np.array(actions), skills


def _first(kind, place_filter, n=80):
    return next(ep for ep in env.make_episodes("train", n) if ep.kind == kind and place_filter(ep))


def test_oracle_solves_a_handful_of_each_difficulty():
    easy = [ep for ep in env.make_episodes("train", 12) if ep.kind == "easy"][:2]
    hard = [_first("object_closed", lambda ep: ep.object_places[ep.target].startswith("drawer")),
            _first("object_closed", lambda ep: ep.object_places[ep.target] == "fridge"),
            _first("goal_closed", lambda ep: True)]
    very_hard = [_first("very_hard", lambda ep: True)]
    seen = set()
    for ep in easy + hard + very_hard:
        info, _, skills = _run_expert(ep)
        assert info["success"], (ep.kind, ep.index, info["failure"])
        seen.update(skills)
    assert {env.SKILL_IDS["open_drawer"], env.SKILL_IDS["open_fridge"]} <= seen


def test_perturbation_snaps_the_drawer_shut_once():
    ep = _first("object_closed", lambda ep: ep.object_places[ep.target].startswith("drawer"))
    e = env.RearrangeEnv(depth_size=8, perturb=True)
    x = expert.Expert(e)
    obs, info = e.reset(seed=0, options={"episode": ep})
    x.reset()
    k = ep.obj_receptacle - 1
    opened_before = False
    while not info["perturbed"]:
        obs, _, term, trunc, info = e.step(x.act(obs)[0])
        opened_before |= e.open_fraction()[k] >= env.OPEN_FRACTION
        assert not (term or trunc), "the perturbation never fired"
    assert opened_before and e.open_fraction()[k] == 0.0 and not info["picked"]


def test_gym_wrapper_passes_env_checker():
    gymnasium = pytest.importorskip("gymnasium")
    from gymnasium.utils.env_checker import check_env
    check_env(env.gym_env(depth_size=8), skip_render_check=True)


def test_fixed_plan_fails_closed_receptacle_and_labels_follow_plan():
    ep = _first("object_closed", lambda ep: ep.object_places[ep.target].startswith("drawer"))
    info, _, skills = _run_expert(ep, plan="fixed")
    assert not info["success"]
    order = [s for i, s in enumerate(skills) if i == 0 or s != skills[i - 1]]
    assert order == [env.SKILL_IDS[s] for s in ("navigate", "pick", "navigate", "place")]


def test_expert_is_deterministic():
    ep = env.make_episodes("train", 1)[0]
    _, a1, _ = _run_expert(ep, seed=3)
    _, a2, _ = _run_expert(ep, seed=3)
    assert np.array_equal(a1, a2)
