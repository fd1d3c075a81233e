"""Evaluate policies by rollouts: the paper's Table 1 (success by difficulty) and Table 2 (perturbation).

A policy is a checkpoint of train.py or ppo.py, checkpoints of one method joined by commas (training seeds: the
table shows mean +- std over them), a scripted expert (`expert:oracle`, our M3 (Oracle): the plan comes from the
simulator; `expert:fixed`: nav, pick, nav, place, like M3; `expert:tpsrl`: that plan with the base still while
the arm works, as TP-SRL), or BC-Modular's skill policies (STEM_<skill>.pt of train.py --skill) under a planner,
`modular:fixed:STEM` and `modular:oracle:STEM` (BC-Modular (Oracle)). Episodes come from a fixed list,
env.make_episodes(split, n, seed=0), reset seeds from (split, episode, rollout seed); a worker runs consecutive
episodes in lock-step batches (--batch), one policy call per step. A rollout depends on its episode, rollout seed
and policy alone, not on --batch or --workers (model.Policy runs the network at a fixed batch: a CPU's kernels
round differently at other sizes, EXPERIMENTS.md R46). Each finished rollout goes to --out's .jsonl at once;
after an interruption, the same command with --resume runs only the missing ones and writes the same tables.

    python evaluate.py --policy ckpt/st.pt --policy expert:oracle --policy expert:fixed \\
                       --episodes 400 --seeds 3 --workers 2                  # Table 1, unseen split
    python evaluate.py --policy ckpt/st_s0.pt,ckpt/st_s1.pt,ckpt/st_s2.pt --split both
    python evaluate.py --policy ckpt/st.pt --policy expert:oracle --perturb  # Table 2 (Sec. 5.4)
    python evaluate.py --policy pretrained/st.pt --episode-seed 1            # a fresh test set
    python evaluate.py --policy modular:fixed:ckpt/bcm --policy modular:oracle:ckpt/bcm   # BC-Modular
    MUJOCO_GL=egl python evaluate.py --policy pretrained/st.pt --picture docs/robot.png  # the README's figure
    python evaluate.py --policy ckpt/st.pt --policy ckpt/ctx15.pt --split both --difficulty easy \\
                       --plot results/fig3.png                               # Sec. 5.5 analysis, Fig. 3

Table 1 (Sec. 5.3): success in % on All, Easy, Hard and Very Hard episodes; the +- is over rollout seeds
(--seeds) with one checkpoint, over training seeds with several. Table 2 (Sec. 5.4): on episodes whose target
starts in a closed drawer, the rate of picking it and the skill accuracy against the Appendix D rule, without and
with the perturbation. An oracle expert beside each rollout labels every state with its skill for two more
measures of the skill module: accuracy against that label, and lock-in (the share of easy episodes' steps on
which it predicts an opening skill). Results go to --out (JSON, every rollout) and its .md (the tables).
"""
import argparse
import json
import multiprocessing as mp
import os
import platform
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from itertools import product

import mujoco
import numpy as np
import torch

import env
import expert
import model


@dataclass
class Config:
    policy: list = field(default_factory=list)
    """CKPT[,CKPT...] (training seeds), expert:oracle|fixed|tpsrl or modular:fixed|oracle:STEM; repeatable"""
    split: str = "unseen"
    """unseen, seen, or both (side by side, as in the paper)"""
    episodes: int = 400
    """episodes per split (with --perturb: episodes whose target starts in a closed drawer)"""
    seeds: int = 1
    """rollout seeds per checkpoint (the +- of a single checkpoint is over these)"""
    workers: int = 2
    """worker processes, each with its own simulators and policies"""
    batch: int = 8
    """episodes a worker runs in lock-step, one policy call for all; keep it to compare runs"""
    perturb: bool = False
    """run the perturbation test (Table 2) instead of Table 1"""
    perturb_after: int = 0
    """with --perturb: steps the receptacle stays open before it snaps shut; 0 keeps the env's 50"""
    episode_seed: int = 0
    """seed of episode lists and reset seeds: 0 for every recorded result (tuned on), else a fresh set, same mix"""
    difficulty: str = ""
    """only episodes of this difficulty (easy, hard, very_hard): the first N of the split that have it"""
    max_steps: int = 0
    """episode step limit for every method; 0 keeps each method's env config"""
    depth_size: int = 0
    """head camera resolution for the experts (checkpoints keep their own); 0 keeps the env default"""
    out: str = "results/eval.json"
    """JSON results; the Markdown tables go next to it with the suffix .md"""
    picture: str = ""
    """draw to this PNG the first --policy solving the first hard or very hard episode it solves, no tables: its path
    from above coloured by skill, beside frames where the skill changes (matplotlib; MUJOCO_GL=egl: RGB, else depth)"""
    log_every: float = 10.0
    """seconds between progress lines"""
    plot: str = ""
    """draw Fig. 3 to this PNG (needs matplotlib); without --policy it redraws from the JSON at --out"""
    resume: bool = False
    """continue an interrupted evaluation: run only the episodes missing from --out's .jsonl"""


EVAL_SEED = 0        # seed of the evaluation episode lists that every result in the record uses
GROUPS = (("all", "All"), ("easy", "Easy"), ("hard", "Hard"), ("very_hard", "Very Hard"))
OPENING = (env.SKILL_IDS["open_drawer"], env.SKILL_IDS["open_fridge"])
CONDITIONS = ("no_perturb", "perturb")


def reset_seed(split, index, rollout_seed, episode_seed=EVAL_SEED):
    """Reset seed of one rollout: a function of the episode and the rollout seed only."""
    return int(np.random.SeedSequence([episode_seed, env.SPLITS[split], index, rollout_seed]).generate_state(1)[0])


def target_in_drawer(episode):
    return episode.obj_receptacle > 0 and env.RECEPTACLES[episode.obj_receptacle - 1].startswith("drawer")


def eval_episodes(split, n, perturb, difficulty="", episode_seed=EVAL_SEED):
    """The fixed episode list: the first n of the split, or the first n that pass the filters (with
    perturb: target in a closed drawer; with difficulty: of that difficulty)."""
    if difficulty and difficulty not in env.DIFFICULTIES:
        raise ValueError(f"--difficulty must be one of {env.DIFFICULTIES} or empty, got {difficulty!r}")
    keep = lambda ep: (not perturb or target_in_drawer(ep)) and (not difficulty or ep.difficulty == difficulty)
    if not perturb and not difficulty:
        return env.make_episodes(split, n, seed=episode_seed)
    drawn = 4 * n
    while True:
        chosen = [ep for ep in env.make_episodes(split, drawn, seed=episode_seed) if keep(ep)]
        if len(chosen) >= n:
            return chosen[:n]
        if drawn > 100 * n + 1000:
            raise ValueError(f"only {len(chosen)} of the first {drawn} {split} episodes pass the filters")
        drawn *= 2


# --- policies ---

def parse_method(spec, cfg):
    """One --policy value -> {name, spec, variant, members: [(ref, env_config)], setting (checkpoints only)}."""
    overrides = {"max_steps": cfg.max_steps} if cfg.max_steps else {}
    if spec.startswith("expert:"):
        plan = spec.split(":", 1)[1]
        if plan not in expert.PLANS:
            raise ValueError(f"unknown expert plan in {spec!r}: expected expert:oracle, expert:fixed or expert:tpsrl")
        kwargs = dict(overrides, **({"depth_size": cfg.depth_size} if cfg.depth_size else {}))
        return {"name": spec, "spec": spec, "variant": f"expert_{plan}",
                "members": [(spec, asdict(env.EnvConfig(**kwargs)))]}
    members, variants, modular, label = [], set(), spec.startswith("modular:"), spec
    if modular:   # modular:PLAN:STEM[,STEM]: STEM_<skill>.pt of train.py --skill
        _, plan, label = (spec.split(":", 2) + ["", ""])[:3]
        if plan not in ModularBatch.SKILLS or not label:
            raise ValueError(f"{spec!r}: expected modular:fixed:STEM or modular:oracle:STEM[,STEM]")
        for stem in label.split(","):
            for s in ModularBatch.SKILLS[plan]:
                policy = model.load_policy(f"{stem}_{s}.pt")
                if policy.variant != "no_skill" or policy.train_config.get("skill") != s:
                    raise ValueError(f"{stem}_{s}.pt is not a BC-Modular {s} policy (train.py --variant "
                                     f"no_skill --skill {s})")
            members.append((f"modular:{plan}:{stem}", dict(policy.env_config, **overrides)))
        variants.add("bc_modular" + ("_oracle" if plan == "oracle" else ""))
    else:
        for path in spec.split(","):
            policy = model.load_policy(path)
            variants.add(policy.train_config.get("variant") or policy.variant)   # ppo.py's "mono": a no_skill net
            members.append((path, dict(policy.env_config, **overrides)))
    if len(variants) > 1:
        raise ValueError(f"{spec}: checkpoints of different variants {sorted(variants)} in one row")
    variant, trained = variants.pop(), policy.train_config   # the last member's: training seeds share the rest
    segments = "" if modular else trained.get("segments") or ""
    setting = {"variant": variant, "context": policy.cfg.context, "memory": policy.cfg.memory,
               "n_demos": trained.get("n_demos"), "segments": segments, "epochs": trained.get("epochs")}
    return {"name": f"{variant} ({label})", "spec": spec, "variant": variant, "members": members, "setting": setting}


# --- one rollout ---

def rollout(policy, envs, episodes, seeds):
    """Run episodes in lock-step, episode i in envs[i], one act_batch call for all -> one result dict per
    episode. The policy gets the previous step's reward (read by the dt variants only). Its skill is scored
    against two labels of the same state: the Appendix D rule (info["skill_gt"]) and the skill an oracle
    expert chooses there (its action is dropped). A finished episode's env stands still while others go on."""
    n = len(episodes)
    obs, infos = map(list, zip(*[e.reset(seed=s, options={"episode": ep}) for e, ep, s in zip(envs, episodes, seeds)]))
    policy.reset()
    labellers = ExpertBatch(envs[:n], "oracle")
    labellers.reset()
    reward, total, steps, done = [0.0] * n, [0.0] * n, [0] * n, [False] * n
    predicted, correct, correct_expert, opening = [0] * n, [0] * n, [0] * n, [0] * n
    while not all(done):
        actions, skills = policy.act_batch(obs, reward)
        for i in (i for i in range(n) if not done[i]):
            label = labellers.experts[i].act(obs[i])[1]
            if skills[i] >= 0:                 # variants without a skill module return -1
                predicted[i] += 1
                correct[i] += int(skills[i]) == int(infos[i]["skill_gt"])
                correct_expert[i] += int(skills[i]) == int(label)
                opening[i] += int(skills[i]) in OPENING
            obs[i], reward[i], terminated, truncated, infos[i] = envs[i].step(actions[i])
            total[i], steps[i], done[i] = total[i] + reward[i], steps[i] + 1, terminated or truncated
    # Where each episode ended, to tell a failed place from a dropped or never-carried object.
    ends = [e.privileged() for e in envs[:n]]
    return [{"index": int(ep.index), "difficulty": ep.difficulty, "kind": ep.kind, "success": bool(info["success"]),
             "picked": bool(info["picked"]), "perturbed": bool(info["perturbed"]), "failure": info["failure"],
             "steps": steps[i], "skill_predicted": predicted[i], "skill_correct": correct[i],
             "skill_correct_expert": correct_expert[i], "skill_opening": opening[i], "return": float(total[i]),
             "held_at_end": bool(end["held"] == ep.target),
             "goal_distance_at_end": float(np.linalg.norm(end["objects"][ep.target] - end["goal"]))}
            for i, (ep, info, end) in enumerate(zip(episodes, infos, ends))]


class ExpertBatch:
    """One scripted expert per env of a lock-step batch, behind the Policy interface."""

    def __init__(self, envs, plan):
        self.experts = [expert.Expert(e, plan=plan) for e in envs]

    def reset(self):
        for x in self.experts:
            x.reset()

    def act_batch(self, obs, rewards):
        out = [x.act(o, r) for x, o, r in zip(self.experts, obs, rewards)]
        return [a for a, _ in out], [z for _, z in out]


class ModularBatch:
    """BC-Modular (Sec. 5.2, Appendix C): a policy per skill (STEM_<skill>.pt, train.py --skill), run in turn
    by a task planner that reads the simulator. plan="fixed": navigate, pick, navigate, place; plan="oracle"
    (BC-Modular (Oracle)): first navigate to and open the goal's, then the object's receptacle if closed at the
    start (the expert's order). A skill ends on its planner condition (arrived; target held; target let go;
    receptacle open, handle let go, arm folded) or on M3's timeout (navigation 500 steps, the others 200); as in
    the paper, a failed skill is not run again. Each skill starts from a fresh context, as its policy was trained."""

    SKILLS = {"fixed": ("navigate", "pick", "place"),
              "oracle": ("navigate", "pick", "place", "open_drawer", "open_fridge")}
    TIMEOUT = {"navigate": 500, "pick": 200, "place": 200, "open_drawer": 200, "open_fridge": 200}

    def __init__(self, envs, stem, plan):
        nets = {s: model.load_policy(f"{stem}_{s}.pt") for s in self.SKILLS[plan]}
        self.envs, self.plan = envs, plan
        self.policies = [{s: model.Policy(p.model, p.env_config, p.rtg_max) for s, p in nets.items()} for _ in envs]
        self.probes = [expert.Expert(e) for e in envs]   # its geometry tells where the robot stands

    def reset(self):
        self.todo, self.steps = [], [0] * len(self.envs)
        for e, probe in zip(self.envs, self.probes):
            p, todo = e.privileged(), []
            for r in (p["episode"].goal_receptacle, p["episode"].obj_receptacle) if self.plan == "oracle" else ():
                if r and p["open_fraction"][r - 1] < expert.NEED_OPEN:
                    todo += [("navigate", r - 1), (probe.open_skill(r - 1), r - 1)]
            self.todo.append(todo + [("navigate", "pick"), ("pick", None), ("navigate", "place"), ("place", None)])
        for policies in self.policies:
            for pol in policies.values():
                pol.reset()

    def _done(self, i):
        """Has env i's current skill met its planner condition?"""
        probe, (skill, arg) = self.probes[i], self.todo[i][0]
        probe.observe()
        p, ep = probe.p, probe.p["episode"]
        obj = p["objects"][ep.target]
        if skill == "navigate" and arg == "pick":
            return probe.at_work(obj, probe.support(obj))
        if skill == "navigate" and arg == "place":
            return probe.at_work(p["goal"], ep.goal_place)
        if skill == "navigate":
            return probe.at_pose(p["poses"]["fridge_door" if env.RECEPTACLES[arg] == "fridge" else "cabinet"])
        if skill == "pick":
            return p["held"] == ep.target
        if skill == "place":
            return p["held"] != ep.target
        return p["open_fraction"][arg] >= expert.NEED_OPEN and p["handle"] < 0 and probe.folded()

    def act_batch(self, obs, rewards):
        actions, skills = [], []
        for i, o in enumerate(obs):
            while self.todo[i] and (self.steps[i] >= self.TIMEOUT[self.todo[i][0][0]] or self._done(i)):
                self.todo[i].pop(0)                       # next skill, whether this one succeeded or not
                self.steps[i] = 0
                if self.todo[i]:
                    self.policies[i][self.todo[i][0][0]].reset()
            if not self.todo[i]:                          # the plan is over: stand still
                actions.append(np.zeros(env.ACTION_DIM, np.float32))
                skills.append(env.SKILL_IDS["place"])
                continue
            skill = self.todo[i][0][0]
            actions.append(self.policies[i][skill].act(o)[0])
            skills.append(env.SKILL_IDS[skill])
            self.steps[i] += 1
        return actions, skills


_envs, _policies = {}, {}   # per worker process: built on first use, reused for later jobs


def actor(ref, env_config, n=1):
    """(policy for n episodes, n envs) for a method member on an env config, built once per process."""
    env_key = json.dumps(env_config, sort_keys=True)
    envs = _envs.setdefault(env_key, [])
    envs += [env.RearrangeEnv(**env_config) for _ in range(n - len(envs))]
    policy_key = (ref, env_key, n) if ref.startswith(("expert:", "modular:")) else (ref, n)   # these read their envs
    if policy_key not in _policies:
        if ref.startswith("expert:"):
            _policies[policy_key] = ExpertBatch(envs[:n], ref.split(":", 1)[1])
        elif ref.startswith("modular:"):
            _, plan, stem = ref.split(":", 2)
            _policies[policy_key] = ModularBatch(envs[:n], stem, plan)
        else:
            _policies[policy_key] = model.load_policy(ref, batch=n)
    return _policies[policy_key], envs[:n]


def rollout_job(job):
    """Worker entry: job = (tags, ref, env_config, episodes, seeds) -> list of tags + rollout result."""
    tags, ref, env_config, episodes, seeds = job
    policy, envs = actor(ref, env_config, len(episodes))
    return [dict(tags, **r) for r in rollout(policy, envs, episodes, seeds)]


def init_worker():
    torch.set_num_threads(1)   # one core per worker process


# --- aggregation ---

def summarize(rollouts):
    """Metrics of one unit (one checkpoint, one rollout seed, one split, one condition), in %."""
    def pct(rows, key, den):
        return 100.0 * sum(r[key] for r in rows) / den if den else None
    groups = {key: [r for r in rollouts if key == "all" or r["difficulty"] == key] for key, _ in GROUPS}
    out = {f"success_{key}": pct(rows, "success", len(rows)) for key, rows in groups.items()}
    picked = [r for r in rollouts if r["picked"]]
    easy = [r for r in rollouts if r["kind"] == "easy"]   # lock-in: opening where nothing needs it
    n, predicted = len(rollouts), sum(r["skill_predicted"] for r in rollouts)
    return dict(out, picked=pct(rollouts, "picked", n), success_given_picked=pct(picked, "success", len(picked)),
                skill_accuracy=pct(rollouts, "skill_correct", predicted),
                skill_accuracy_expert=pct(rollouts, "skill_correct_expert", predicted),
                opening_share_easy=pct(easy, "skill_opening", sum(r["skill_predicted"] for r in easy)),
                perturbed=pct(rollouts, "perturbed", n), mean_length=float(np.mean([r["steps"] for r in rollouts])))


def spread(units, key):
    """Mean and std of a metric: over training seeds when there are several, else over rollout seeds;
    std None for a single run (one checkpoint, one rollout seed), which has no measured spread."""
    if any(u[key] is None for u in units):
        return None
    members = sorted({u["member"] for u in units})
    values = ([np.mean([u[key] for u in units if u["member"] == m]) for m in members] if len(members) > 1
              else [u[key] for u in units])
    return {"mean": float(np.mean(values)), "std": float(np.std(values)) if len(values) > 1 else None}


def aggregate(method, rollouts):
    """All rollouts of one method on one split and condition -> {metric: {mean, std}, failures, units}."""
    units = []
    for ref, _ in method["members"]:
        for seed in sorted({r["seed"] for r in rollouts}):
            mine = [r for r in rollouts if r["member"] == ref and r["seed"] == seed]
            units.append(dict(member=ref, seed=seed, episodes=len(mine), **summarize(mine)))
    metrics = {key: spread(units, key) for key in units[0] if key not in ("member", "seed", "episodes")}
    failures = Counter(r["failure"] or ("none" if r["success"] else "unknown") for r in rollouts)
    return dict(metrics, failures=dict(sorted(failures.items())), units=units)


# --- tables ---

def fmt(stat):
    if stat is None:
        return "-"
    return f"{stat['mean']:.2f}" if stat["std"] is None else f"{stat['mean']:.2f} ± {stat['std']:.2f}"


def markdown(results):
    cfg, splits, methods, lines = results["config"], results["splits"], results["methods"], []

    def table(title, header, rows):
        lines.extend([f"## {title}", "", "| " + " | ".join(header) + " |",
                      "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows] + [""])

    if not cfg["perturb"]:
        prefix = (lambda s: s.capitalize() + " ") if len(splits) > 1 else (lambda s: "")
        header = ["Method"] + [prefix(s) + label for s in splits for _, label in GROUPS]
        rows = [[m["name"]] + [fmt(m["results"][s]["no_perturb"][f"success_{g}"]) for s in splits for g, _ in GROUPS]
                for m in methods]
        table(f"Table 1: success rate (%), {' and '.join(splits)}, {cfg['episodes']} episodes per split", header, rows)
    else:
        for s in splits:
            header = ["Method", "Pick No Perturb", "Pick Perturb", "Skill Acc No Perturb", "Skill Acc Perturb"]
            rows = [[m["name"]] + [fmt(m["results"][s][c][k]) for k in ("picked", "skill_accuracy") for c in CONDITIONS]
                    for m in methods]
            table(f"Table 2: picking the target and skill accuracy (%), {s}, {cfg['episodes']} episodes "
                  f"with the target in a closed drawer", header, rows)
    details = dict(picked="Picked", success_given_picked="Success given picked",
                   skill_accuracy="Skill accuracy (App. D rule)", skill_accuracy_expert="Skill accuracy (expert label)",
                   opening_share_easy="Opening skill on easy", perturbed="Perturbed")
    header = ["Method", "Condition", *details.values(), "Mean length", "Failures (last step)"]
    for s in splits:
        rows = [[m["name"], c] + [fmt(r[k]) for k in details]
                + [f"{r['mean_length']['mean']:.0f}", ", ".join(f"{k} {v}" for k, v in r["failures"].items())]
                for m in methods for c, r in m["results"][s].items()]
        table(f"Details: {s}", header, rows)
    return "\n".join(lines)


# --- Fig. 3 ---

FIG3 = (("variant", "architecture (Fig. 3a)"), ("context", "context length C (Fig. 3b)"), ("memory", "memory tokens"),
        ("n_demos", "demonstrations (Fig. 3c)"), ("segments", "partial demonstrations (Sec. 5.5)"))


def fig3_panels(methods):
    """Checkpoint methods -> [(key, title, methods)], one per Fig. 3 panel that has something to
    compare: the reference run and the runs that differ from it in that one setting only. The
    reference is the run that the most others differ from in exactly one setting."""
    runs = [m for m in methods if m.get("setting")]
    diff = lambda a, b: [k for k in a["setting"] if a["setting"][k] != b["setting"][k]]
    if not runs:
        return []
    ref = max(runs, key=lambda m: sum(len(diff(m, o)) == 1 for o in runs))
    panels = []
    for key, title in FIG3:
        members = [ref] + [m for m in runs if diff(m, ref) == [key]]
        if isinstance(ref["setting"][key], int):
            members.sort(key=lambda m: m["setting"][key])
        if len(members) > 1:
            panels.append((key, title, members))
    return panels


def pyplot():
    try:
        import matplotlib
        matplotlib.use("Agg")                   # no display: draw to a file
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise ValueError("--plot and --picture need matplotlib (pip install matplotlib); the tables do not") from err
    return plt


def plot_fig3(results, path):
    """Fig. 3 as bars: a column per panel, success (top) and picked (bottom) per split, +- std."""
    plt = pyplot()
    panels = fig3_panels(results["methods"])
    if not panels:
        raise ValueError(f"--plot: no two checkpoints in {results['config']['out']} differ in just one of "
                         f"{[k for k, _ in FIG3]}, so there is no panel to draw")
    splits, width = results["splits"], 0.8 / len(results["splits"])
    fig, axes = plt.subplots(2, len(panels), figsize=(4 * len(panels), 6), squeeze=False)
    for col, (key, title, members) in enumerate(panels):
        x = np.arange(len(members))
        for row, (metric, label) in enumerate((("success_all", "success (%)"), ("picked", "picked (%)"))):
            ax = axes[row][col]
            for i, s in enumerate(splits):
                stats = [m["results"][s]["no_perturb"][metric] for m in members]
                xs = x + (i - (len(splits) - 1) / 2) * width
                ax.bar(xs, [st["mean"] for st in stats], width, label=s)
                spread_ = [(xi, st) for xi, st in zip(xs, stats) if st["std"] is not None]
                if spread_:                          # an error bar only where seeds measured a spread
                    ax.errorbar([xi for xi, _ in spread_], [st["mean"] for _, st in spread_],
                                yerr=[st["std"] for _, st in spread_], fmt="none", capsize=3, color="k")
            ax.set_xticks(x, [str(m["setting"][key] or "whole") for m in members])
            ax.set_ylabel(label)
        axes[0][col].set_title(title)
    axes[0][0].legend(title=results["config"]["difficulty"] or "all episodes")
    fig.tight_layout()
    fig.savefig(path + ".tmp", format="png", dpi=120)
    os.replace(path + ".tmp", path)             # atomic: no half-written PNG
    plt.close(fig)


# --- the README figure: one rollout from above, and frames ---

def rgb_renderer(e, size=240):
    """A third-person RGB view following the robot, or None without OpenGL (MUJOCO_GL=egl needs no display)."""
    if not (os.environ.get("MUJOCO_GL") or os.environ.get("DISPLAY")):
        return None                             # GLFW, the default, needs a display
    try:
        renderer = mujoco.Renderer(e.model, size, size)
    except Exception:  # no display and no EGL / OSMesa: mujoco raises several kinds
        return None
    cam, option = mujoco.MjvCamera(), mujoco.MjvOption()
    cam.distance, cam.elevation = 3.0, -60.0
    option.geomgroup[:] = 1   # the robot's geoms are in a group the renderer hides by default

    def render():
        x, y, yaw = e.data.qpos[e.ids["base_q"]]
        cam.lookat[:] = (x, y, 0.5)
        cam.azimuth = np.degrees(yaw)   # from behind the robot, looking where it heads
        renderer.update_scene(e.data, camera=cam, scene_option=option)
        return renderer.render()
    return render


SKILL_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


def record_rollout(policy, e, episode, seed, min_run=10):
    """One episode, per step the base pose and the predicted skill, and a frame (RGB where OpenGL works,
    else the head depth) at the first step and wherever a new skill starts that lasts min_run steps
    -> (success, poses (T, 3), skills (T,), [(step, skill, frame)])."""
    obs, info = e.reset(seed=seed, options={"episode": episode})
    render = rgb_renderer(e)                    # after the reset: a renderer belongs to the layout's model
    policy.reset()
    poses, skills, frames, reward, done = [], [], {}, 0.0, False
    while not done:
        actions, z = policy.act_batch([obs], [reward])
        poses.append(e.privileged()["base"])
        if not skills or int(z[0]) != skills[-1]:
            frames[len(skills)] = render() if render else env.depth_to_uint8(obs["depth"])
        skills.append(int(z[0]))
        obs, reward, terminated, truncated, info = e.step(actions[0])
        done = terminated or truncated
    skills = np.array(skills)
    keep = [t for t in sorted(frames) if t == 0 or (skills[t:t + min_run] == skills[t]).all()]
    return info["success"], np.array(poses), skills, [(t, skills[t], frames[t]) for t in keep]


def draw_picture(cfg, method, path):
    """The README's picture (see Config.picture)."""
    plt = pyplot()
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Polygon
    ref, env_config = method["members"][0]
    policy, (e,) = actor(ref, env_config)
    split = "unseen" if cfg.split == "both" else cfg.split
    tried = 0
    for ep in (ep for ep in eval_episodes(split, cfg.episodes, False, episode_seed=cfg.episode_seed)
               if ep.difficulty != "easy"):
        tried += 1
        seed = reset_seed(split, ep.index, 0, cfg.episode_seed)
        success, poses, skills, frames = record_rollout(policy, e, ep, seed)
        if success:
            break
    else:
        raise ValueError(f"--picture: {method['name']} solved none of the {tried} hard or very hard episodes among "
                         f"the first {cfg.episodes} {split} ones")
    frames = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, min(6, len(frames))).round().astype(int))]
    fig = plt.figure(figsize=(13, 6))
    grid = fig.add_gridspec(2, 5, width_ratios=[1.6, 1.6, 1, 1, 1])
    ax = fig.add_subplot(grid[:, :2])
    layout = e.layout
    ax.add_patch(Polygon([(0, 0), (layout.room[0], 0), layout.room, (0, layout.room[1])], fill=False, lw=2))
    opened = [r for r, frac in enumerate(e.open_fraction()) if frac > env.OPEN_FRACTION]
    for f in layout.furniture:
        corners = [env._local_to_world(f, (sx * f.size[0] / 2, sy * f.size[1] / 2))
                   for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1))]
        held = [env.RECEPTACLES[r].replace("_", " ") for r in opened
                if (env.RECEPTACLES[r] == "fridge") == (f.kind == "fridge") and f.kind in ("cabinet", "fridge")]
        ax.add_patch(Polygon(corners, color="tab:red" if held else "0.75", alpha=0.5))
        ax.text(*f.center, f.name.replace("_", " ") + "".join(f"\n({h} opened)" for h in held), ha="center",
                va="center", fontsize=8)
    segments = np.stack([poses[:-1, :2], poses[1:, :2]], 1)
    ax.add_collection(LineCollection(segments, colors=[SKILL_COLORS[z] for z in skills[:-1]], lw=2.5))
    ax.plot(*poses[0, :2], "k^", ms=9, label="robot start")
    ax.plot(*ep.objects[ep.target][:2], "r*", ms=14, label="target start")
    ax.plot(*ep.goal[:2], "gX", ms=12, label="goal")
    for z, name in enumerate(env.SKILLS):
        ax.plot([], [], color=SKILL_COLORS[z], lw=3, label=name)
    ax.set(xlim=(-0.2, layout.room[0] + 0.2), ylim=(-0.2, layout.room[1] + 0.2), aspect="equal", xticks=[], yticks=[])
    ax.legend(loc="upper left", bbox_to_anchor=(0, -0.01), ncol=4, fontsize=8, frameon=False)
    ax.set_title(f"{method['name']}: {split} episode {ep.index} ({ep.kind.replace('_', ' ')}), "
                 f"solved in {len(skills)} steps", fontsize=10)
    for i, (t, z, frame) in enumerate(frames):
        fa = fig.add_subplot(grid[i // 3, 2 + i % 3])
        fa.imshow(frame, cmap="gray")
        fa.set(xticks=[], yticks=[])
        fa.set_title(f"step {t}: {env.SKILLS[z]}", fontsize=9, color=SKILL_COLORS[z])
    fig.tight_layout()
    fig.savefig(path + ".tmp", format="png", dpi=100)
    os.replace(path + ".tmp", path)
    plt.close(fig)
    print(f"wrote {path}: {split} episode {ep.index}, the first solved of {tried} hard or very hard tried"
          + ("" if frames[0][2].ndim == 3 else "; head depth frames (RGB needs OpenGL: MUJOCO_GL=egl)"), flush=True)


# --- results files ---

# the settings that make two runs the same evaluation (--batch, --workers and the rest only set speed)
IDENTITY = ("policy", "split", "episodes", "seeds", "perturb", "perturb_after", "episode_seed", "difficulty",
            "max_steps", "depth_size")


def rollout_key(r):
    return r["method"], r["member"], r["seed"], r["split"], r["condition"], r["index"]


def append_line(f, obj):
    """One JSON line in one write, flushed to disk: a kill leaves at most a partial last line."""
    f.write(json.dumps(obj) + "\n")
    f.flush()
    os.fsync(f.fileno())


def read_rollout_log(path, identity):
    """The rollouts an interrupted run of the same evaluation left in its .jsonl (a partial last line
    dropped, the file rewritten without it) -> list of rollout dicts; [] when there is no file."""
    if not os.path.exists(path):
        print(f"--resume: no {path} yet, starting fresh", flush=True)
        return []
    with open(path) as f:
        lines = f.read().split("\n")
    rows = []
    for line in lines[:-1]:                         # the part after the last newline is incomplete
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: a corrupt line inside the file ({err}); remove the file to start over") from err
    if not rows or rows[0].get("evaluation") != json.loads(json.dumps(identity)):
        raise ValueError(f"{path} records another evaluation ({rows[0].get('evaluation') if rows else 'nothing'}); "
                         f"this run is {identity}: use another --out, or run without --resume to replace it")
    write_atomic(path, "".join(line + "\n" for line in lines[:-1]))
    return rows[1:]


def write_atomic(path, text):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


# --- main ---

def evaluate(cfg):
    """Run all rollouts, aggregate, write --out and its .md -> the results dict."""
    if cfg.split not in ("seen", "unseen", "both"):
        raise ValueError(f"--split must be seen, unseen or both, got {cfg.split!r}")
    if not cfg.policy:
        raise ValueError("give at least one --policy (a checkpoint, expert:oracle or expert:fixed)")
    if cfg.episode_seed < 0:
        raise ValueError(f"--episode-seed must be >= 0, got {cfg.episode_seed}")
    if cfg.batch < 1 or cfg.workers < 1 or cfg.episodes < 1 or cfg.seeds < 1:
        raise ValueError(f"--batch, --workers, --episodes and --seeds must be >= 1, got {cfg.batch}, "
                         f"{cfg.workers}, {cfg.episodes}, {cfg.seeds}")
    splits = ["seen", "unseen"] if cfg.split == "both" else [cfg.split]
    methods = [parse_method(spec, cfg) for spec in cfg.policy]
    conditions = CONDITIONS if cfg.perturb else CONDITIONS[:1]
    episodes = {s: eval_episodes(s, cfg.episodes, cfg.perturb, cfg.difficulty, cfg.episode_seed) for s in splits}
    # Rollouts already in --out's .jsonl are kept with --resume: a rollout depends on its episode, seed and
    # policy alone (model.Policy runs the network at a fixed batch), so resuming gives the same results.
    log_path, settings = os.path.splitext(cfg.out)[0] + ".jsonl", asdict(cfg)
    identity = {k: v for k, v in settings.items() if k in IDENTITY}
    rollouts = read_rollout_log(log_path, identity) if cfg.resume else []
    finished = {rollout_key(r) for r in rollouts}
    # A job is a lock-step batch of cfg.batch consecutive episodes of the fixed list, less those finished.
    chunks = {s: [episodes[s][k:k + cfg.batch] for k in range(0, len(episodes[s]), cfg.batch)] for s in splits}
    after = {"perturb_after": cfg.perturb_after} if cfg.perturb_after else {}
    jobs = []
    for i, m in enumerate(methods):
        for (ref, env_config), seed, s, c in product(m["members"], range(cfg.seeds), splits, conditions):
            tags = {"method": i, "member": ref, "seed": seed, "split": s, "condition": c}
            for chunk in chunks[s]:
                left = [ep for ep in chunk if rollout_key(dict(tags, index=ep.index)) not in finished]
                if left:
                    jobs.append((tags, ref, dict(env_config, perturb=c == "perturb", **after), left,
                                 [reset_seed(s, ep.index, seed, cfg.episode_seed) for ep in left]))
    n_total = len(rollouts) + sum(len(job[3]) for job in jobs)
    print(f"evaluating {len(methods)} methods on {', '.join(splits)}: {n_total} rollouts in batches of "
          f"{cfg.batch}, {cfg.workers} workers" + (f"; {len(rollouts)} already in {log_path}" if rollouts else ""),
          flush=True)
    n_before, t0, last_log = len(rollouts), time.time(), time.time()
    pool = mp.get_context("spawn").Pool(cfg.workers, initializer=init_worker) if cfg.workers > 1 else None
    if pool is None:
        init_worker()   # in-process too: torch's default of every core fights a training beside it
    os.makedirs(os.path.dirname(os.path.abspath(log_path)), exist_ok=True)
    try:
        with open(log_path, "a" if rollouts else "w") as log:
            if not rollouts:
                append_line(log, {"evaluation": identity})
            for batch in (pool.imap_unordered(rollout_job, jobs) if pool else map(rollout_job, jobs)):
                for r in batch:
                    append_line(log, r)
                rollouts += batch
                now = time.time()
                if now - last_log >= cfg.log_every or len(rollouts) == n_total:
                    last_log, rate = now, (len(rollouts) - n_before) / ((now - t0) / 60)
                    print(f"[{len(rollouts):5d}/{n_total}] {rate:6.1f} ep/min, "
                          f"eta {(n_total - len(rollouts)) / rate:.1f} min", flush=True)
    finally:
        if pool:
            pool.terminate() if len(rollouts) < n_total else pool.close()
            pool.join()
    rollouts.sort(key=rollout_key)
    for i, m in enumerate(methods):
        mine = [r for r in rollouts if r["method"] == i]
        m["results"] = {s: {c: aggregate(m, [r for r in mine if (r["split"], r["condition"]) == (s, c)])
                            for c in conditions} for s in splits}
    config = {k: v for k, v in settings.items() if k != "resume"}   # a resumed run: the same file
    results = {"config": config, "eval_seed": cfg.episode_seed, "splits": splits,
               "versions": {"python": platform.python_version(), "numpy": np.__version__,
                            "mujoco": mujoco.__version__, "torch": torch.__version__},
               "methods": methods, "rollouts": rollouts}
    results["markdown"] = markdown(results)
    write_atomic(cfg.out, json.dumps(results, indent=1))
    write_atomic(os.path.splitext(cfg.out)[0] + ".md", results["markdown"])
    return results


# --- command line ---

def parse_args(argv=None):
    """argparse generated from Config (env.add_config_args)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    return Config(**vars(env.add_config_args(p, Config).parse_args(argv)))


if __name__ == "__main__":
    cfg = parse_args()
    try:
        if cfg.plot:
            pyplot()                            # fail now, not after an hour of rollouts
        if cfg.picture:
            if not cfg.policy:
                raise ValueError("--picture needs a --policy")
            pyplot()
            init_worker()
            draw_picture(cfg, parse_method(cfg.policy[0], cfg), cfg.picture)
            sys.exit(0)
        if cfg.plot and not cfg.policy:         # redraw from an earlier run
            with open(cfg.out) as f:
                results = json.load(f)
        else:
            results = evaluate(cfg)
            print(results["markdown"])
            print(f"wrote {cfg.out} and {os.path.splitext(cfg.out)[0]}.md")
        if cfg.plot:
            plot_fig3(results, cfg.plot)
            print(f"wrote {cfg.plot}")
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"error: {err}")
