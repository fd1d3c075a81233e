"""Collect expert demonstrations for imitation learning, one `.npz` per episode.

Runs the privileged oracle expert of `expert.py` (our stand-in for the paper's M3 (Oracle) data-generating policy,
Appendix C.1) on `train` episodes in parallel worker processes and records, per step, what the paper records:
observations, actions, rewards and the executing skill. The stored action is always the expert's clean label for the
state the step shows. Three ways to show a learner states off the expert's path (EXPERIMENTS.md records each):

- DART (Laskey et al. 2017): the env executes the expert's action plus noise (`--noise`; `--nav-noise`: turn drift).
- Perturbation events (`--events R` per 1,000 steps): an open receptacle is shut, the base pushed, or the held
  target dropped; the expert, a function of the state, recovers in the demo.
- DAgger (Ross et al. 2011, `--policy CKPT`): a trained policy drives, the expert labels every state. Each segment
  of `--segment` steps is driven by the expert with probability `--beta` (0: the policy drives all). Every episode
  is kept, solved or not; train on the union with the expert's demos (train.py --data DIR,DIR).

    python collect.py --out data/demos                    # the recipe: 1,000 demos, DART noise, events
    python collect.py --out data/priv --obs privileged    # the same demos with receptacle_open in the state
    python collect.py --episodes 300 --out data/dagger --seed 1 --policy ckpt/st.pt --beta 0.5
    python collect.py --stats data/demos

Determinism: episode index k runs `env.make_episodes("train", ..., seed=S)[k]` with a reset seed derived from
(S, k), which also seeds the noise, the events and the DAgger segments, so a file's bytes never depend on the worker
count. Without `--keep-failed` (or `--policy`) indices are judged in order and the first N successes are kept.
Files are written to a temporary name and renamed, so rerunning the same command after a kill resumes.

File format 3 (readable with `numpy.load(path, allow_pickle=False)`), T steps:
    depth uint8 (T, H, W), state float32 (T, D) in meta.json's state_layout (D = 30 with obs="paper", 32 with
    "privileged"), action float32 (T, 10) clean expert action, skill int8 (T,), receptacle int8 (T,) auxiliary
    label of the observed state, receptacle_open float32 (T, 2) how open the target's and the goal's receptacles
    are (a training target, env.RearrangeEnv._receptacle_open), reward float32 (T,) received after the action;
    events int64 (3,) perturbation events of the episode: shut, push, drop (EVENTS);
    scalars: success bool, layout int, difficulty str, seed int (reset seed), index int.
"""
import argparse
import dataclasses
import json
import multiprocessing as mp
import os
import platform
import re
import sys
import time
from collections import deque

import mujoco
import numpy as np

import env
import expert


@dataclasses.dataclass
class Config:
    episodes: int = 1000
    """number of demonstrations to write (successful ones unless --keep-failed or --policy)"""
    out: str = "data/demos"
    """output directory: ep_{k:06d}.npz files and meta.json"""
    workers: int = 2
    """worker processes, each with its own simulator"""
    seed: int = 0
    """dataset seed: selects the train episodes and the reset seeds"""
    obs: str = "paper"
    """observation mode (env.OBS_MODES): paper, the recipe; privileged adds receptacle_open to the state"""
    noise: float = 0.1
    """DART noise scale injected into the executed actions (the stored action stays clean; 0: none)"""
    nav_noise: float = 0.2
    """DART drift of the executed turn rate while navigating (expert.Expert's nav_noise; 0: none)"""
    events: float = 3.0
    """perturbation rate per 1,000 steps (shut, push, drop; 0: none); 3 solved more than 1 (EXPERIMENTS.md R47)"""
    policy: str = ""
    """DAgger: this train.py checkpoint drives, the expert labels every step; keeps every episode, solved or not"""
    beta: float = 0.0
    """DAgger: probability that the (noised) expert drives a segment, not the --policy (0: the policy drives all)"""
    segment: int = 10
    """DAgger: steps per segment; who drives is drawn at the start of each"""
    keep_failed: bool = False
    """also keep demonstrations in which the expert failed"""
    depth_size: int = 0
    """head camera resolution in pixels; 0 keeps the env.EnvConfig default"""
    max_steps: int = 0
    """episode step limit; 0 keeps the env.EnvConfig default"""
    log_every: float = 10.0
    """seconds between progress lines"""
    stats: str = ""
    """print statistics of the dataset in this directory and exit"""


FORMAT_VERSION = 3   # 2 added the events array, 3 the receptacle_open target
EPISODE_FILE = re.compile(r"^ep_(\d{6})\.npz$")
TEMP_FILE = re.compile(r"^ep_(\d{6})\.npz\.\d+\.tmp$")   # ep_k.npz.<pid>.tmp
# meta.json entries that must agree before new episodes are added to an existing directory
MUST_MATCH = ("format", "env_config", "seed", "noise", "nav_noise", "events", "keep_failed", "plan",
              "policy", "beta", "segment", "release_zone")


def episode_path(out, k):
    return os.path.join(out, f"ep_{k:06d}.npz")


def reset_seed(seed, k):
    """Reset seed of episode k: a function of (dataset seed, index) only, never of the schedule."""
    return int(np.random.SeedSequence([seed, k]).generate_state(1)[0])


# --- validation ---

EVENTS = ("shut", "push", "drop")
STEP_ARRAYS = {"depth": np.uint8, "state": np.float32, "action": np.float32, "skill": np.int8,
               "receptacle": np.int8, "receptacle_open": np.float32, "reward": np.float32}
TRAILING_SHAPE = {"action": (env.ACTION_DIM,), "skill": (), "receptacle": (), "receptacle_open": (2,), "reward": ()}
SCALARS = {"success": "b", "layout": "iu", "difficulty": "U", "seed": "iu", "index": "iu"}


def load_episode(path, state_dim):
    """Load and validate one demonstration file whose state has state_dim numbers per step (meta.json's
    state_layout) -> dict of numpy arrays; ValueError naming the file."""
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except Exception as err:  # zip, zlib, pickle or OS errors all mean the same thing here
        raise ValueError(f"{path}: not a readable demonstration .npz ({type(err).__name__}: {err})") from err
    missing = sorted((set(STEP_ARRAYS) | set(SCALARS) | {"events"}) - set(data))
    if missing:
        raise ValueError(f"{path}: missing keys {missing}; not a collect.py demonstration (format {FORMAT_VERSION})")
    T = len(data["action"]) if data["action"].ndim else 0
    if T < 1:
        raise ValueError(f"{path}: expected at least one step, got action of shape {data['action'].shape}")
    for key, dtype in STEP_ARRAYS.items():
        a = data[key]
        if a.dtype != dtype:
            raise ValueError(f"{path}: {key} has dtype {a.dtype}, expected {np.dtype(dtype)}")
        want = {"depth": (T, *data["depth"].shape[1:]), "state": (T, state_dim)}.get(key) or (T, *TRAILING_SHAPE[key])
        if a.shape != want or (key == "depth" and a.ndim != 3):
            raise ValueError(f"{path}: {key} has shape {a.shape}, expected {want} (T={T}, depth (T, H, W))")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError(f"{path}: {key} has non-finite values")
    for key, kinds in SCALARS.items():
        if data[key].shape != () or data[key].dtype.kind not in kinds:
            raise ValueError(f"{path}: {key} should be a scalar of kind {kinds!r}, "
                             f"got shape {data[key].shape} dtype {data[key].dtype}")
    ev = data["events"]
    if ev.shape != (len(EVENTS),) or ev.dtype.kind not in "iu" or (ev < 0).any():
        raise ValueError(f"{path}: events should be {len(EVENTS)} counts >= 0 ({', '.join(EVENTS)}), "
                         f"got shape {ev.shape} dtype {ev.dtype}")
    for key, top in (("skill", len(env.SKILLS) - 1), ("receptacle", len(env.RECEPTACLES))):   # receptacle 0: none
        if not (0 <= data[key].min() and data[key].max() <= top):
            raise ValueError(f"{path}: {key} labels outside [0, {top}]")
    if not np.isin(data["action"][:, env.GRIP], env.GRIP_VALUES).all():
        raise ValueError(f"{path}: grip commands (action[:, {env.GRIP}]) outside {env.GRIP_VALUES}")
    if str(data["difficulty"]) not in env.DIFFICULTIES:
        raise ValueError(f"{path}: difficulty {data['difficulty']!r} not in {env.DIFFICULTIES}")
    return data


# --- perturbation events ---

SHUT_OPEN = 0.3            # a receptacle open more than this fraction can be shut ...
SHUT_CLEAR = 0.5           # m: ... while the cup is farther than this from its handle and not over
                           # its furniture (an arm reaching into the fridge is far from the door's handle)
PUSH_DIST = (0.1, 0.3)     # m: a push moves the base this far, in a direction drawn uniformly,
PUSH_YAW = 0.3             # rad: and turns it by up to this much either way
DROP_CLEAR = env.ROBOT_RADIUS + 0.05   # m: the held target is dropped this far from the base centre (not on the robot)


def applicable_events(e, x):
    """The events that apply now -> {kind: its choices} (for shut: the receptacles). x (expert.Expert) has acted on
    this state; its support() names the place under a point, so a receptacle is not shut on the arm and the target is
    dropped above a surface or receptacle. A receptacle is shut only where the head camera sees its handle: the expert
    goes back to open it, which a learner can imitate only if it could see why (env.py's rule)."""
    p = e.privileged()
    over = x.support(p["ee"])
    cabinet = over.startswith("drawer")                  # the drawers are stacked: over one is near both
    # not the goal's receptacle while the target is carried: opening it would mean putting the target down anywhere
    carried = p["held"] == p["target"]
    shut = [k for k, r in enumerate(env.RECEPTACLES)
            if p["open_fraction"][k] > SHUT_OPEN and np.linalg.norm(p["ee"] - p["handles"][k]) > SHUT_CLEAR
            and over != r and not (cabinet and r.startswith("drawer"))
            and not (carried and k == p["goal_receptacle"] - 1) and e.in_view(p["handles"][k])]
    push = p["handle"] < 0    # a base pushed while the cup holds a handle tears at the weld: a collision
    obj = p["objects"][p["target"]]
    under = x.support(obj)   # a drawer's region reaches out over its travel: it must stand open
    drop = (p["held"] == p["target"] and under != "floor" and np.hypot(*(obj[:2] - p["base"][:2])) > DROP_CLEAR
            and (not under.startswith("drawer") or p["open_fraction"][env.RECEPTACLES.index(under)] > SHUT_OPEN))
    return {kind: choices for kind, choices in zip(EVENTS, (shut, [None] * bool(push), [None] * bool(drop))) if choices}


def perturb(e, x, rng):
    """One event, its kind drawn uniformly among those that apply now -> its index in EVENTS, or None
    when none applies or the push drawn would put the base into the scene (env.push_base refuses it)."""
    events = applicable_events(e, x)
    if not events:
        return None
    kind = list(events)[rng.integers(len(events))]
    if kind == "shut":
        e.close_receptacle(events["shut"][rng.integers(len(events["shut"]))])
    elif kind == "push":
        dist, angle, dyaw = rng.uniform(*PUSH_DIST), rng.uniform(-np.pi, np.pi), rng.uniform(-PUSH_YAW, PUSH_YAW)
        if not e.push_base(dist * np.cos(angle), dist * np.sin(angle), dyaw):
            return None
    else:
        e.drop()
    return EVENTS.index(kind)


# --- one episode (runs in a worker) ---

_worker_env, _worker_policy = {}, {}   # per process: simulator and policy, built on the first job


def record_episode(e, episode, seed, noise=0.0, nav_noise=0.0, events=0.0, policy=None, beta=0.0, segment=10):
    """Run one episode -> dict of arrays in the file format, the stored action the oracle's clean
    label. Executed: the expert's noised action, or a policy's in the segments the expert (probability
    beta) does not drive. Before a step, with probability events / 1000, an event (perturb) strikes."""
    x = expert.Expert(e, plan="oracle", seed=seed, noise=noise, nav_noise=nav_noise)
    obs, info = e.reset(seed=seed, options={"episode": episode})
    x.reset()
    if policy is not None:
        policy.reset()
    # two streams of the reset seed: the events drawn do not depend on whether a policy drives
    drive_rng, event_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    steps = {k: [] for k in STEP_ARRAYS}
    counts = np.zeros(len(EVENTS), np.int64)
    reward, done, expert_drives, t = 0.0, False, True, 0
    while not done:
        action, skill = x.act(obs)
        steps["depth"].append(env.depth_to_uint8(obs["depth"]))
        steps["state"].append(env.state_vector(obs, e.state_layout))
        steps["action"].append(action)
        steps["skill"].append(skill)
        steps["receptacle"].append(info["receptacle"])   # labels of the state this obs shows
        steps["receptacle_open"].append(info["receptacle_open"])
        executed = x.noisy(action)                        # every step, whoever drives: the noise runs on
        if policy is not None:
            learned, _ = policy.act(obs, reward)          # every step: its context is the whole episode
            if t % segment == 0:
                expert_drives = drive_rng.random() < beta
            if not expert_drives:
                executed = learned
        # the event strikes after this step's observation and label, so both show the same state
        if events > 0 and event_rng.random() < events / 1000:
            kind = perturb(e, x, event_rng)
            if kind is not None:
                counts[kind] += 1
        obs, reward, terminated, truncated, info = e.step(executed)
        steps["reward"].append(reward)
        done, t = terminated or truncated, t + 1
    data = {k: np.asarray(v, dtype=STEP_ARRAYS[k]) for k, v in steps.items()}
    data.update(events=counts, success=np.bool_(info["success"]), layout=np.int64(episode.layout),
                difficulty=np.str_(episode.difficulty), seed=np.int64(seed), index=np.int64(episode.index))
    return data


def collect_job(job):
    """Worker entry: record episode k to a temporary file -> (temporary path, success, steps)."""
    k, episode, seed, cfg, env_kwargs = job
    key = json.dumps(env_kwargs, sort_keys=True)
    if key not in _worker_env:
        _worker_env.clear()
        _worker_env[key] = env.RearrangeEnv(**env_kwargs)
    if cfg.policy and cfg.policy not in _worker_policy:
        import torch, model                             # DAgger only: a later stage, imported here
        torch.set_num_threads(1)                        # one core per worker process
        _worker_policy[cfg.policy] = model.load_policy(cfg.policy)
    data = record_episode(_worker_env[key], episode, seed, cfg.noise, cfg.nav_noise, cfg.events,
                          _worker_policy.get(cfg.policy), cfg.beta, cfg.segment)
    tmp = f"{episode_path(cfg.out, k)}.{os.getpid()}.tmp"   # per process: an orphaned worker of a killed
    with open(tmp, "wb") as f:                              # run cannot write into this run's file
        np.savez_compressed(f, **data)                      # (a file object: savez adds no suffix)
    return tmp, bool(data["success"]), len(data["action"])


# --- the dataset directory ---

def make_meta(cfg, env_kwargs):
    return {"format": FORMAT_VERSION, "env_config": dataclasses.asdict(env.EnvConfig(**env_kwargs)),
            "state_layout": [[k, n] for k, n in env.state_layout(cfg.obs)], "skills": list(env.SKILLS),
            "receptacles": list(env.RECEPTACLES), "difficulties": list(env.DIFFICULTIES), "split": "train",
            "plan": "oracle", "seed": cfg.seed, "noise": cfg.noise, "nav_noise": cfg.nav_noise, "events": cfg.events,
            "keep_failed": cfg.keep_failed or bool(cfg.policy),   # a DAgger set keeps every episode
            "release_zone": expert.RELEASE_ZONE,                   # the place's release label
            "policy": cfg.policy or None,                          # DAgger: null for the expert's own demos
            "beta": cfg.beta if cfg.policy else None, "segment": cfg.segment if cfg.policy else None,
            "versions": {"python": platform.python_version(), "numpy": np.__version__, "mujoco": mujoco.__version__}}


def check_or_write_meta(out, meta):
    """Write meta.json, or refuse a directory that holds another dataset."""
    path = os.path.join(out, "meta.json")
    meta = json.loads(json.dumps(meta))   # tuples -> lists, as they come back from disk
    if not os.path.exists(path):
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "w") as f:
            json.dump(meta, f, indent=2)
        os.replace(tmp, path)
        return
    try:
        with open(path) as f:
            old = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: unreadable meta.json ({err})") from err
    diff = [k for k in MUST_MATCH if old.get(k) != meta.get(k)]
    if diff:
        detail = "; ".join(f"{k}: directory has {old.get(k)!r}, this run wants {meta.get(k)!r}" for k in diff)
        raise ValueError(f"{path} records another dataset ({detail}). Use another --out, or the "
                         f"same settings to resume.")
    if old.get("versions") != meta["versions"]:
        print(f"note: {path} was written with {old.get('versions')}, now {meta['versions']}")


def remove_temps(out):
    """Remove temporary files: partial results of a killed run or of unfinished jobs."""
    for name in filter(TEMP_FILE.match, os.listdir(out)):
        os.remove(os.path.join(out, name))


def read_episodes(out, state_dim):
    """Validate every .npz in out, in name order -> yields (k, episode dict) per ep_{k:06d}.npz."""
    for name in sorted(n for n in os.listdir(out) if n.endswith(".npz")):
        path = os.path.join(out, name)
        m = EPISODE_FILE.match(name)
        if not m:
            raise ValueError(f"{path}: foreign .npz in the dataset directory (expected ep_NNNNNN.npz)")
        yield int(m.group(1)), load_episode(path, state_dim)


# --- main loop ---

def check_policy(path, env_kwargs):
    """A --policy must be a train.py checkpoint for the env config this dataset records."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"--policy {path}: checkpoint not found")
    want = dataclasses.asdict(env.EnvConfig(**env_kwargs))
    import model                                        # DAgger only: a later stage, imported here
    got = model.load_checkpoint(path)["env_config"]
    diff = sorted(k for k in want if got.get(k) != want[k])
    if diff:
        raise ValueError(f"--policy {path} was trained on env_config {', '.join(f'{k}={got.get(k)!r}' for k in diff)}; "
                         f"this dataset records {', '.join(f'{k}={want[k]!r}' for k in diff)}")


def collect(cfg):
    """Write cfg.episodes demonstrations to cfg.out; returns a summary."""
    need = cfg.episodes
    max_draws = 10 * need + 20   # more failures than this: give up with a clear error
    env_kwargs = {"obs": cfg.obs, **{k: getattr(cfg, k) for k in ("depth_size", "max_steps") if getattr(cfg, k)}}
    keep_all = cfg.keep_failed or bool(cfg.policy)   # DAgger: the labels are valid, solved or not
    if not 0 <= cfg.events <= 1000:
        raise ValueError(f"--events is a rate per 1,000 steps in [0, 1000], got {cfg.events}")
    if not (0 <= cfg.beta <= 1 and cfg.segment >= 1):
        raise ValueError(f"--beta must be in [0, 1] and --segment >= 1, got {cfg.beta} and {cfg.segment}")
    state_dim = sum(n for _, n in env.state_layout(cfg.obs))   # ValueError for an unknown --obs
    if not cfg.policy and (cfg.beta, cfg.segment) != (Config.beta, Config.segment):
        raise ValueError(f"--beta and --segment mix a --policy's actions with the expert's; "
                         f"got --beta {cfg.beta} --segment {cfg.segment} without --policy")
    if cfg.policy:
        check_policy(cfg.policy, env_kwargs)
    os.makedirs(cfg.out, exist_ok=True)
    check_or_write_meta(cfg.out, make_meta(cfg, env_kwargs))
    remove_temps(cfg.out)
    have = {k: {key: d[key].item() for key in ("success", "index", "seed", "layout", "difficulty")}
            for k, d in read_episodes(cfg.out, state_dim)}   # the files already there, validated
    episodes = []   # make_episodes("train", ..., cfg.seed), grown as needed
    pool = mp.get_context("spawn").Pool(cfg.workers) if cfg.workers > 1 else None
    # (k, None for a file already there | AsyncResult | job to run here), in index order; judged in
    # that order, with enough in flight that a long episode at the head does not idle the workers
    pending = deque()
    kept = kept_here = drawn = ran = ran_success = steps = 0
    t0 = last_log = time.time()
    try:
        while kept < need:
            while not pending or (len(pending) < 8 * cfg.workers and kept + len(pending) < need):
                if drawn >= max_draws:
                    raise RuntimeError(f"only {kept}/{need} demonstrations after {drawn} episode indices: "
                                       "the expert rarely succeeds with these settings")
                k, drawn = drawn, drawn + 1   # indices are drawn in order: 0, 1, 2, ...
                if k >= len(episodes):
                    episodes = env.make_episodes("train", max(k + 1, 2 * len(episodes), 64), seed=cfg.seed)
                episode, seed = episodes[k], reset_seed(cfg.seed, k)
                if k in have:   # a file already there must hold this dataset's episode k
                    want = {"index": k, "seed": seed, "layout": int(episode.layout), "difficulty": episode.difficulty}
                    got = {key: have[k][key] for key in want}
                    if got != want:
                        raise ValueError(f"{episode_path(cfg.out, k)}: holds {got}, but this dataset's episode {k} "
                                         f"is {want} (a file from another dataset?)")
                    pending.append((k, None))
                    continue
                job = (k, episode, seed, cfg, env_kwargs)
                pending.append((k, pool.apply_async(collect_job, (job,)) if pool else job))
            k, work = pending.popleft()
            if work is None:
                success = have[k]["success"]
            else:
                tmp, success, n_steps = work.get() if pool else collect_job(work)
                ran, ran_success, steps = ran + 1, ran_success + success, steps + n_steps
                if success or keep_all:
                    os.replace(tmp, episode_path(cfg.out, k))   # atomic: a file is whole or absent
                else:
                    os.remove(tmp)
            kept += success or keep_all
            kept_here += work is not None and (success or keep_all)
            now = time.time()
            if now - last_log >= cfg.log_every or kept == need:
                last_log, minutes = now, max(now - t0, 1e-9) / 60
                eta = f"{(need - kept) / kept_here * minutes:.1f} min" if kept_here else "?"
                print(f"[{kept:5d}/{need}] {ran / minutes:6.1f} ep/min, success {ran_success}/{ran} run here, "
                      f"{steps / minutes / 60:6.0f} steps/s, eta {eta}", flush=True)
    finally:
        if pool:   # pending is empty once the last needed episode is in; else stop the workers now
            pool.terminate() if pending else pool.close()
            pool.join()
        remove_temps(cfg.out)
    return {"kept": kept, "drawn": drawn, "ran": ran, "ran_success": ran_success, "seconds": time.time() - t0}


# --- statistics ---

def dataset_stats(out):
    """Summary of a dataset directory (every file validated) -> dict."""
    size = sum(os.path.getsize(os.path.join(out, n)) for n in os.listdir(out))
    try:
        with open(os.path.join(out, "meta.json")) as f:
            state_dim = sum(n for _, n in json.load(f)["state_layout"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{out}/meta.json: missing or unreadable ({err}); is {out!r} written by collect.py?") from err
    skills, events = np.zeros(len(env.SKILLS), np.int64), np.zeros(len(EVENTS), np.int64)
    lengths, still, inner = [], 0, 0
    by_diff = {d: [0, 0] for d in env.DIFFICULTIES}
    for _, data in read_episodes(out, state_dim):
        skills += np.bincount(data["skill"], minlength=len(env.SKILLS))
        by_diff[str(data["difficulty"])][0] += 1
        by_diff[str(data["difficulty"])][1] += bool(data["success"])
        lengths.append(len(data["action"]))
        events += data["events"]
        a = data["action"][:-30]                # a label that waits: still arm, still base, no grip
        still += int(((np.abs(a[:, :9]).max(1) < 0.02) & (a[:, 9] == 0)).sum())
        inner += len(a)
    n = len(lengths)
    return {"episodes": n, "steps": int(sum(lengths)),
            "steps_min_mean_max": [min(lengths, default=0), float(np.mean(lengths)) if n else 0.0,
                                   max(lengths, default=0)],
            "skill_steps": {s: int(c) for s, c in zip(env.SKILLS, skills)},
            "success": sum(v[1] for v in by_diff.values()) / max(n, 1),
            "by_difficulty": {d: {"episodes": v[0], "success": v[1] / max(v[0], 1)} for d, v in by_diff.items()},
            "events_per_episode": {k: float(v) / max(n, 1) for k, v in zip(EVENTS, events)},
            "still_share": still / max(inner, 1), "bytes": size}


def print_stats(out):
    s = dataset_stats(out)
    lo, mean, hi = s["steps_min_mean_max"]
    print(f"{out}: {s['episodes']} episodes, {s['steps']} steps (per episode min {lo}, mean {mean:.0f}, max {hi})")
    print(f"success {100 * s['success']:.1f}%")
    total = max(s["steps"], 1)
    print("skill steps: " + ", ".join(f"{k} {v} ({100 * v / total:.1f}%)" for k, v in s["skill_steps"].items()))
    for d, v in s["by_difficulty"].items():
        print(f"  {d:9s} {v['episodes']:6d} episodes, success {100 * v['success']:.1f}%")
    print("events per episode: " + ", ".join(f"{k} {v:.2f}" for k, v in s["events_per_episode"].items()))
    print(f"still labels (|arm|, |base| < 0.02, grip keep) outside the last 30 steps: {100 * s['still_share']:.2f}%")
    print(f"size on disk {s['bytes'] / 2**20:.1f} MiB ({s['bytes'] / 2**10 / max(s['episodes'], 1):.0f} KiB/episode)")
    return s


# --- command line ---

def parse_args(argv=None):
    """argparse generated from Config (env.add_config_args)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    return Config(**vars(env.add_config_args(p, Config).parse_args(argv)))


if __name__ == "__main__":
    cfg = parse_args()
    try:
        if cfg.stats:
            print_stats(cfg.stats)
        else:
            print(f"collecting {cfg.episodes} demonstrations into {cfg.out}: {cfg}", flush=True)
            r = collect(cfg)
            print(f"done: {r['kept']} demonstrations in {cfg.out}; ran {r['ran']} episodes "
                  f"({r['ran_success']} successful) in {r['seconds'] / 60:.1f} min", flush=True)
    except (ValueError, RuntimeError, FileNotFoundError) as err:
        sys.exit(f"error: {err}")
