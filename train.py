"""Imitation learning of the Skill Transformer (and baselines) from expert demonstrations.

Follows Sec. 4.2 and Appendix A of the paper: random windows of C steps from the demos, the losses computed at every
step of the window, AdamW, an "epoch" of 80 randomly chosen demonstrations, a linear learning-rate warm-up from 1e-8
followed by a cosine decay to 0. The defaults are the README's recipe; its departures from the paper, each a flag with
the experiment that set it (EXPERIMENTS.md): C = 15, not 30 (R20); memory tokens of older steps (R48); part of the
steps feed action inference the skill module's own prediction instead of the true skill (--skill-sample 0.5; 0 is the
paper's teacher forcing; R5); the skill and auxiliary losses weighted (R4); and the last checkpoint is kept, not the
one of the best success on a few `seen` episodes (with the 20 or so a CPU affords, that choice is noise).

    python train.py --data data/demos --out ckpt/st.pt                    # Skill Transformer, the recipe
    python train.py --data data/demos --out ckpt/dt.pt --variant dt       # or no_skill, lstm, dt_skill
    python train.py --data data/demos --out ckpt/st.pt --resume           # continue ckpt/st.last.pt, if any
    python train.py --data data/demos --out ckpt/part.pt --segments nav-pick,nav-place   # Sec. 5.5
    for s in navigate pick place open_drawer open_fridge; do                           # BC-Modular
        python train.py --data data/demos --variant no_skill --skill $s --out ckpt/bcm_$s.pt; done
    python train.py --data data/demos,data/dagger --out ckpt/st2.pt       # DAgger: the union of demo dirs
    python train.py --data data/heldout --validate ckpt/st.pt,ckpt/dt.pt   # fit on held-out demos
    torchrun --nproc_per_node=2 train.py --data data/demos --out ckpt/st.pt   # DDP (gloo on CPU)

For --out ckpt/st.pt it writes ckpt/st.pt (the final model), ckpt/st.last.pt (every epoch: the optimizer, the
schedule's position and every random generator's state, so that a run killed at any moment and resumed ends with the
same weights, bit for bit, as one never stopped) and ckpt/st.csv (the losses). The defaults take about 50 min alone on
2 CPU cores for 1,000 demos (~19,000 iterations).
"""
import argparse
import contextlib
import csv
import datetime
import glob
import json
import math
import os
import random
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel as DDP

import collect
import env
import model


@dataclass
class TrainConfig:
    """Training run; every field is a command-line flag (--warmup-epochs 5 or --warmup_epochs=5)."""
    data: str = "data/demos"
    """directory of ep_XXXXXX.npz demos and meta.json, written by collect.py (several: DIR,DIR)"""
    out: str = "ckpt/st.pt"
    """checkpoint to write; CKPT.last.pt and CKPT.csv go beside it"""
    variant: str = "st"
    """st (Skill Transformer), no_skill, lstm, dt or dt_skill"""
    context: int = 15
    """context length C in steps (Sec. 4.1: 30; 15 solved more here, EXPERIMENTS.md R20)"""
    memory: int = 12
    """older steps read as state-only memory tokens before the window (model.ModelConfig; 0: none)"""
    memory_stride: int = 40
    """steps between memory tokens"""
    d_model: int = 128
    """transformer width; the visual and state embeddings get half each (paper: 512)"""
    near_scale: float = 0.1
    """metres: > 0 also feeds tanh(v / near_scale) of the reach targets (model.NEAR_FIELDS); 0: off"""
    n_layer: int = 2
    """layers per transformer (Sec. 4.1)"""
    n_head: int = 4
    """attention heads"""
    dropout: float = 0.0
    """dropout in the transformers; off: on a CPU it costs ~15% of a step"""
    epochs: int = 300
    """epochs of demos_per_epoch demos: 24 passes over 1,000 demos (150 solved 9 points less, R28, R29)"""
    warmup_epochs: int = 20
    """epochs of linear warm-up from lr_start to lr (Appendix A: 200 of 750 epochs)"""
    demos_per_epoch: int = 80
    """demonstrations drawn at random for each epoch (Appendix A: 80)"""
    batch_size: int = 64
    """windows per optimizer step (summed over DDP ranks); 64 keeps both CPU cores busy"""
    lr: float = 5e-4
    """peak learning rate; the paper's 6e-5 (Appendix A) suits far more updates than our ~19,000"""
    lr_start: float = 1e-8
    """learning rate at the start of the warm-up (Appendix A)"""
    weight_decay: float = 0.1
    """AdamW weight decay on weight matrices (not on biases, norms, embeddings of position)"""
    prev_action: bool = False
    """a_{t-1} tokens in action inference (paper); off: with them the policy copies a_{t-1} (copycat, EXPERIMENTS.md)"""
    skill_sample: float = 0.5
    """st/lstm: probability that a step's z_t is the skill module's own argmax instead of the true skill (scheduled
    sampling); 0: the paper's teacher forcing"""
    skill_weight: float = 0.3
    """weight of the skill loss (Eq. 1; the paper's: 1). On data/v10 the encoder gradient norms of
    skill, aux, arm, base, grip were 2-4, 5-9, 0.2-0.9, 0.7-2.7, 0.1-0.2: at 1 they swamp the actions"""
    aux_weight: float = 0.1
    """weight of the auxiliary receptacle loss (Eq. 3) in the sum (the paper's: 1); see skill_weight"""
    open_weight: float = 0.1
    """weight of the auxiliary loss on how open the target's and the goal's receptacles are"""
    grad_clip: float = 1.0
    """clip the gradient norm to this (0: off)"""
    seed: int = 0
    """seed of random, numpy and torch; the same seed draws the same windows"""
    max_demos: int = 0
    """use only the first N demos in file order (0: all)"""
    segments: str = ""
    """train on pieces of the demos only, e.g. nav-pick,nav-place (Sec. 5.5), an epoch taking as many
    pieces as hold demos_per_epoch demos' steps (the same budget); empty: whole demos"""
    skill: str = ""
    """BC-Modular (Sec. 5.2): train a policy for this skill alone (no_skill variant), on the runs of steps the demos
    label with it, an epoch drawing the runs of demos_per_epoch demos: the five together take one run's budget;
    evaluate.py --policy modular:fixed:STEM sequences them"""
    resume: bool = False
    """continue from CKPT.last.pt (same model, same data env config); without one, start fresh"""
    log_interval: int = 10
    """iterations between log lines and CSV rows (mean losses)"""
    grad_norms: bool = False
    """also log each loss term's gradient norm on the shared encoder (five more backward passes per log line;
    how the loss weights were chosen, EXPERIMENTS.md R4)"""
    device: str = "auto"
    """auto (cuda if available), cpu or cuda"""
    threads: int = 0
    """torch CPU threads per process (0: all cores divided among the DDP ranks)"""
    validate: str = ""
    """CKPT[,CKPT]: train nothing; print and write to CKPT.val.json the fit per skill on the demos
    of --data, with the true and with the predicted skills as z"""


LOSS_TERMS = ("loss", "skill", "aux", "open", "arm", "base", "grip")
GRAD_COLUMNS = tuple(f"grad_{k}" for k in LOSS_TERMS[1:])   # each term's gradient norm on the encoder
CSV_FIELDS = ("epoch", "iter", "lr") + LOSS_TERMS + GRAD_COLUMNS + ("ms_iter", "samples_s")
SEGMENTS = {"nav-pick": "pick", "nav-place": "place"}   # --segments: the skill each piece ends with (cut_segments)
BATCH_KEYS = ("depth", "state", "action", "prev_action", "skill", "receptacle", "receptacle_open", "rtg")


# --- learning-rate schedule (Appendix A) ---

def get_lr(epoch, cfg):
    """Learning rate at a (fractional) epoch: linear from lr_start to lr over warmup_epochs, then cosine decay to 0 at
    cfg.epochs. The paper steps it once per epoch; we step it per iteration (epoch + it / iters): ~15x fewer epochs."""
    if epoch < cfg.warmup_epochs:
        return cfg.lr_start + (cfg.lr - cfg.lr_start) * epoch / cfg.warmup_epochs
    progress = min(1.0, (epoch - cfg.warmup_epochs) / max(cfg.epochs - cfg.warmup_epochs, 1e-9))
    return 0.5 * cfg.lr * (1.0 + math.cos(math.pi * progress))


# --- data ---

def load_meta(data_dir):
    """meta.json of a demo directory, checked against env's vocabulary."""
    path = os.path.join(data_dir, "meta.json")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path} not found: is {data_dir!r} a directory written by collect.py?")
    try:
        with open(path) as f:
            meta = json.load(f)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from e
    if meta.get("format") != collect.FORMAT_VERSION:
        raise ValueError(f"{path}: data format {meta.get('format')!r}, expected {collect.FORMAT_VERSION}: collect anew")
    mode = meta.get("env_config", {}).get("obs")
    if mode not in env.OBS_MODES:
        raise ValueError(f"{path}: env_config.obs is {mode!r}, expected one of {env.OBS_MODES}")
    expect = json.loads(json.dumps({"skills": env.SKILLS, "receptacles": env.RECEPTACLES,
                                    "state_layout": env.state_layout(mode)}))   # tuples -> lists, as on disk
    for key, want in expect.items():
        if meta.get(key) != want:
            raise ValueError(f"{path}: {key} is {meta.get(key)!r}, this code expects {want!r}")
    return meta


def load_episode(path, size, state_dim):
    """One demo .npz, checked by collect.load_episode -> dict of its step arrays, prev_action and rtg (add_inputs)."""
    data = collect.load_episode(path, state_dim)
    if data["depth"].shape[1:] != (size, size):
        raise ValueError(f"{path}: depth has shape {data['depth'].shape}, expected (T, {size}, {size})")
    return add_inputs({k: data[k].astype(np.int64) if k in ("skill", "receptacle") else data[k]
                       for k in collect.STEP_ARRAYS})


def add_inputs(ep):
    """The inputs a demo implies: prev_action a_{t-1} (zero at its first step) and rtg R_t."""
    ep["prev_action"] = np.concatenate([np.zeros((1, env.ACTION_DIM), np.float32), ep["action"][:-1]])
    ep["rtg"] = np.cumsum(ep["reward"][::-1])[::-1].astype(np.float32)  # R_t = sum of rewards from t on
    return ep


def cut_segments(demos, names):
    """Sec. 5.5, incomplete demonstrations: keep of each demo only the navigation that leads to a skill plus the skill
    itself (nav-pick, nav-place), each piece a demo of its own."""
    bad = [n for n in names if n not in SEGMENTS]
    if bad:
        raise ValueError(f"segments {bad}: expected names from {tuple(SEGMENTS)}, joined by commas")
    nav, pieces = env.SKILL_IDS["navigate"], []
    for ep in demos:
        for name in names:
            idx = np.flatnonzero(ep["skill"] == env.SKILL_IDS[SEGMENTS[name]])
            if len(idx):
                start = idx[0]
                while start > 0 and ep["skill"][start - 1] == nav:
                    start -= 1
                pieces.append(add_inputs({k: ep[k][start:idx[-1] + 1] for k in collect.STEP_ARRAYS}))
    return pieces


def same_steps_per_epoch(demos_per_epoch, whole, pieces):
    """Pieces per epoch that hold as many steps as demos_per_epoch whole demos (lengths `whole`): the same iterations
    as on whole demos (80 nav-pick and nav-place pieces hold a third of 80 demos' steps, a third of the training)."""
    return max(1, round(demos_per_epoch * np.mean(whole) / np.mean(pieces)))


def skill_runs(demos, skill):
    """BC-Modular: every maximal run of steps labelled with the skill, each a demo of its own (a skill policy starts
    from a fresh context, as the planner starts it in a rollout)."""
    if skill not in env.SKILL_IDS:
        raise ValueError(f"--skill {skill!r}: expected one of {env.SKILLS}")
    pieces = []
    for ep in demos:
        edges = np.flatnonzero(np.diff(np.r_[0, (ep["skill"] == env.SKILL_IDS[skill]).astype(np.int8), 0]))
        pieces += [add_inputs({k: ep[k][a:b] for k in collect.STEP_ARRAYS}) for a, b in zip(edges[::2], edges[1::2])]
    if not pieces:
        raise ValueError(f"no step of the demos is labelled {skill!r}")
    return pieces


def dict_diff(a, b):
    """'key: a vs b' for each key whose values differ between two dicts (a missing key counts); '' if none."""
    return ", ".join(f"{k}: {a.get(k)!r} vs {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k))


def load_demos(data, max_demos=0):
    """All demos of a directory, or of several joined by commas (DAgger's aggregate: the demos and the data
    collect.py --policy added), in memory (depth stays uint8) -> (list of episode dicts, first directory's meta)."""
    dirs = data.split(",")
    metas = [load_meta(d) for d in dirs]
    meta, files = metas[0], []
    for d, m in zip(dirs, metas):
        diff = dict_diff(m["env_config"], meta["env_config"])
        if diff:
            raise ValueError(f"{d}/meta.json: env_config differs from {dirs[0]}/meta.json in {diff}")
        found = sorted(glob.glob(os.path.join(d, "ep_*.npz")))
        if not found:
            raise ValueError(f"no ep_*.npz files in {d!r}")
        files += found
    size, state_dim = int(meta["env_config"]["depth_size"]), sum(n for _, n in meta["state_layout"])
    return [load_episode(f, size, state_dim) for f in files[:max_demos or None]], meta   # max_demos 0: all


def epoch_windows(lengths, cfg, epoch, per_epoch=0):
    """Appendix A: an epoch draws demos_per_epoch demos (or per_epoch pieces); windows end at steps drawn uniformly
    from theirs, as many as cover each step once, in whole batches. The same (seed, epoch) gives the same windows on
    every rank, which takes its share of each batch. -> (n, 2) int array of (demo, end step)."""
    rng = np.random.default_rng([cfg.seed, epoch])
    chosen = rng.choice(len(lengths), size=min(per_epoch or cfg.demos_per_epoch, len(lengths)), replace=False)
    ends = every_step(lengths, chosen)
    B = cfg.batch_size
    n = max(B, int(round(len(ends) / cfg.context)) // B * B)   # each step about once per epoch
    return ends[rng.choice(len(ends), size=n, replace=n > len(ends))]


def every_step(lengths, demos):
    """(n, 2) int array of (demo, step) for every step of the given demos, in order."""
    return np.concatenate([np.stack([np.full(lengths[i], i), np.arange(lengths[i])], 1) for i in demos])


def flatten_demos(demos, device):
    """All demos end to end in one tensor per array on the training device (a GPU holds ~1 GB of depth per 1,000
    demos): a batch is one gather, not a Python loop. -> ({key: (N_steps, ...) tensor}, (n_demos,) first rows)."""
    starts = np.concatenate([[0], np.cumsum([len(d["action"]) for d in demos])[:-1]])
    flat = {k: torch.from_numpy(np.concatenate([d[k] for d in demos])).to(device) for k in BATCH_KEYS}
    return flat, torch.as_tensor(starts, device=device)


def get_batch(flat, starts, windows, C, memory=0, stride=1):
    """Windows (B, 2) of (demo, end step) -> batch of (B, C, ...) tensors, and the states of the `memory` steps at
    `stride` before each window (mem_state (B, M, S), oldest first: what a rollout's Policy keeps). A window starting
    before step 0 is left-padded with zeros; mask (mem_mask) marks the real steps; padding is out of every loss."""
    windows = torch.as_tensor(windows, device=starts.device)
    first = starts[windows[:, 0]][:, None]                              # (B, 1) row of each demo's step 0

    def gather(keys, t):                                                # t (B, L) steps of the demo
        mask = t >= 0
        idx = first + t.clamp(min=0)
        return {k: flat[k][idx] * mask.view(*mask.shape, *[1] * (flat[k].dim() - 1)) for k in keys}, mask

    batch, mask = gather(BATCH_KEYS, windows[:, 1:] + torch.arange(1 - C, 1, device=starts.device))
    B, S = mask.shape[0], flat["depth"].shape[-1]
    batch["depth"] = batch["depth"].float().div_(255.0).view(B, C, 1, S, S)  # (B, T, 1, H, W) in [0, 1]
    batch["mask"] = mask
    if memory:
        back = torch.arange(memory, 0, -1, device=starts.device) * stride      # M x stride, ..., stride
        mem, batch["mem_mask"] = gather(("state",), windows[:, 1:] + 1 - C - back)
        batch["mem_state"] = mem["state"]
    return batch


def grad_norm(loss, params):
    """L2 norm of d loss / d params, leaving the graph for the backward pass of the total loss."""
    grads = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return float(sum((g.float() ** 2).sum() for g in grads if g is not None) ** 0.5)


def data_stats(demos):
    """State normalisation and return scales, stored in the model / checkpoint."""
    state = np.concatenate([d["state"] for d in demos])
    rtg_abs = max(float(np.abs(d["rtg"]).max()) for d in demos)
    return {"state_mean": state.mean(0), "state_std": np.maximum(state.std(0), 0.05),
            "rtg_scale": rtg_abs if rtg_abs > 0 else 1.0,
            "rtg_max": max(float(d["rtg"][0]) for d in demos)}  # Appendix C.2: max return of the demos


# --- checkpoints ---

def stem(path):
    return path[:-3] if path.endswith(".pt") else path


def save_atomic(obj, path):
    """torch.save to a temporary file, flushed to disk, then renamed: a kill leaves the old file or the new one."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        torch.save(obj, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def rng_states():
    """Every random generator a training step may draw from (scheduled sampling and dropout draw from torch's), in a
    form torch.load(weights_only=True) reads back."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            "numpy": (kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, cached),
            "python": random.getstate()}


def set_rng_states(s):
    torch.set_rng_state(s["torch"])
    if s["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(s["cuda"])
    kind, keys, pos, has_gauss, cached = s["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    random.setstate(s["python"])


def open_log(path, iter_num=None):
    """CKPT.csv, its header written, open to append rows -> (file, csv.DictWriter). A resumed run (iter_num) keeps the
    old rows up to the checkpoint it restarts from (it writes the later ones again)."""
    rows = []
    if iter_num is not None and os.path.exists(path):
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("iter", "").isdigit() and int(r["iter"]) <= iter_num]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, CSV_FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)
    f = open(path, "a", newline="")
    return f, csv.DictWriter(f, CSV_FIELDS)


def check_model_args(ckpt, margs, ckpt_path):
    """Resuming or fine-tuning needs the same network as the checkpoint's."""
    have = {**asdict(model.ModelConfig()), **ckpt["model_args"]}   # a field added later: its default
    diff = dict_diff(have, asdict(margs))
    if diff:
        raise ValueError(f"{ckpt_path}: model settings differ from the command line's (checkpoint vs now): {diff}")


def check_env_config(ckpt, meta, ckpt_path, data_dir):
    """A model trained on one env config must not be trained or compared on data from another."""
    diff = dict_diff(ckpt["env_config"], meta["env_config"])
    if diff:
        raise ValueError(f"{ckpt_path} was trained with env_config different from {data_dir}/meta.json in {diff}")


# --- training ---

def train(cfg):
    """Runs the whole training; returns the path of the main checkpoint (rank 0)."""
    ddp = int(os.environ.get("RANK", -1)) != -1
    if cfg.device == "auto":
        cfg.device = "cuda" if torch.cuda.is_available() else "cpu"
    rank, local_rank, world = 0, 0, 1
    if ddp:
        dist.init_process_group("nccl" if cfg.device == "cuda" else "gloo", timeout=datetime.timedelta(hours=2))
        rank, local_rank, world = dist.get_rank(), int(os.environ["LOCAL_RANK"]), dist.get_world_size()
    device = torch.device(f"cuda:{local_rank}" if cfg.device == "cuda" else "cpu")
    if device.type == "cuda":
        torch.cuda.set_device(device)
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.benchmark = True
    torch.set_num_threads(cfg.threads or max(1, (os.cpu_count() or 1) // int(os.environ.get("LOCAL_WORLD_SIZE", 1))))
    if not 0 <= cfg.skill_sample <= 1:
        raise ValueError(f"skill_sample must lie in [0, 1], got {cfg.skill_sample}")
    if cfg.batch_size % world:
        raise ValueError(f"batch_size ({cfg.batch_size}) must be a multiple of the DDP world size ({world})")
    B = cfg.batch_size // world  # windows per rank and step
    master = rank == 0
    log = print if master else (lambda *a, **k: None)
    for seed in (random.seed, np.random.seed, torch.manual_seed):
        seed(cfg.seed + rank)   # dropout differs per rank; DDP broadcasts rank 0's init
    autocast = torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda" else contextlib.nullcontext()

    # data
    t0 = time.time()
    demos, meta = load_demos(cfg.data, cfg.max_demos)
    n_demos = len(demos)  # the dataset size (Fig. 3c), also when the demos are cut into pieces
    if cfg.skill and cfg.variant != "no_skill":
        raise ValueError(f"--skill trains one BC-Modular skill policy: use --variant no_skill, not {cfg.variant}")
    per_epoch = 0  # an epoch: demos_per_epoch demos
    if cfg.segments:
        whole = [len(d["action"]) for d in demos]
        demos = cut_segments(demos, cfg.segments.split(","))
        per_epoch = same_steps_per_epoch(cfg.demos_per_epoch, whole, [len(d["action"]) for d in demos])
    if cfg.skill:
        demos = skill_runs(demos, cfg.skill)
        per_epoch = round(cfg.demos_per_epoch * len(demos) / n_demos)  # the runs of demos_per_epoch demos
    lengths = [len(d["action"]) for d in demos]
    pieces = cfg.segments or (cfg.skill and "runs of " + cfg.skill)
    log(f"loaded {len(demos)} {'pieces (' + pieces + ')' if pieces else 'demos'}, {sum(lengths)} steps, "
        f"depth {demos[0]['depth'].shape[1]}px from {cfg.data} in {time.time() - t0:.1f} s")

    # model
    margs = model.ModelConfig(
        depth_size=int(meta["env_config"]["depth_size"]), state_layout=tuple((k, n) for k, n in meta["state_layout"]),
        n_skills=len(env.SKILLS), n_receptacles=len(env.RECEPTACLES) + 1, context=cfg.context, memory=cfg.memory,
        memory_stride=cfg.memory_stride, d_vis=cfg.d_model // 2, d_state=cfg.d_model - cfg.d_model // 2,
        d_model=cfg.d_model, near_scale=cfg.near_scale, n_layer=cfg.n_layer, n_head=cfg.n_head, dropout=cfg.dropout,
        variant=cfg.variant, prev_action=cfg.prev_action, skill_sample=cfg.skill_sample)
    last_path, csv_path = stem(cfg.out) + ".last.pt", stem(cfg.out) + ".csv"
    ckpt, start_epoch, iter_num = None, 0, 0
    if cfg.resume and not os.path.isfile(last_path):
        log(f"--resume: no {last_path} yet, starting fresh")
    elif cfg.resume:
        ckpt = model.load_checkpoint(last_path)
        check_env_config(ckpt, meta, last_path, cfg.data)
        check_model_args(ckpt, margs, last_path)
        if ckpt["config"].get("seed") != cfg.seed:
            raise ValueError(f"{last_path} was trained with --seed {ckpt['config'].get('seed')}, not {cfg.seed}")
        start_epoch, iter_num = ckpt["epoch"], ckpt["iter_num"]
        log(f"resuming {last_path} at epoch {start_epoch}")
    raw = model.SkillTransformer(margs)   # net: raw, or its DDP wrapper
    stats = data_stats(demos)
    flat, starts = flatten_demos(demos, device)
    del demos  # the flat copy is all training needs
    for k in ("state_mean", "state_std", "rtg_scale"):
        getattr(raw, k).copy_(torch.as_tensor(stats[k]))
    raw.to(device)
    log(f"{cfg.variant}: {raw.num_params() / 1e6:.2f}M parameters, device {device}, world {world}, "
        f"{torch.get_num_threads()} threads")

    # AdamW with weight decay on weight matrices only (nanoGPT)
    params = [p for p in raw.parameters() if p.requires_grad]
    decay = [p for p in params if p.dim() >= 2 and p is not raw.pos_emb]
    groups = [{"params": decay, "weight_decay": cfg.weight_decay},
              {"params": [p for p in params if p.dim() < 2 or p is raw.pos_emb], "weight_decay": 0.0}]
    opt = torch.optim.AdamW(groups, lr=cfg.lr_start, betas=(0.9, 0.95))
    if ckpt is not None:
        raw.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        set_rng_states(ckpt["rng"][rank])   # the generators as they stood at the end of that epoch
    net = DDP(raw, device_ids=[local_rank] if device.type == "cuda" else None) if ddp else raw

    def checkpoint(epoch, rng=None):
        # The optimizer and generator states (2/3 of the bytes) go only into CKPT.last.pt, which --resume reads:
        # with them the resumed run takes the very steps the uninterrupted one takes.
        return {"model": {k: v.cpu() for k, v in raw.state_dict().items()},  # loads without a GPU
                "optimizer": opt.state_dict() if rng else None, "rng": rng, "model_args": asdict(margs),
                "config": asdict(cfg), "epoch": epoch, "iter_num": iter_num, "env_config": meta["env_config"],
                "rtg_max": stats["rtg_max"], "n_demos": n_demos, "skills": list(env.SKILLS)}

    # each term's gradient on the encoder that all terms train (R4), with --grad-norms only
    encoder = [p for m in (raw.vis, raw.state_mlp, raw.tok_proj) for p in m.parameters()]
    if master:
        csv_file, writer = open_log(csv_path, None if ckpt is None else iter_num)
    sums, n_sum, first_iter, t_start, t_int = {}, 0, iter_num, time.time(), time.time()
    for epoch in range(start_epoch, cfg.epochs):
        windows = epoch_windows(lengths, cfg, epoch, per_epoch)
        iters = len(windows) // cfg.batch_size
        if epoch == start_epoch:
            log(f"epoch = {min(per_epoch or cfg.demos_per_epoch, len(lengths))} {'pieces' if pieces else 'demos'}, "
                f"{len(windows)} windows of {cfg.context} steps, {iters} iterations of {cfg.batch_size} windows")
        raw.train()
        for it in range(iters):
            lr = get_lr(epoch + it / iters, cfg)
            for g in opt.param_groups:
                g["lr"] = lr
            mine = windows[it * cfg.batch_size + rank * B:it * cfg.batch_size + (rank + 1) * B]
            batch = get_batch(flat, starts, mine, cfg.context, cfg.memory, cfg.memory_stride)
            with autocast:
                out = net(batch)
            losses = raw.compute_loss(out, batch, cfg.skill_weight, cfg.aux_weight, cfg.open_weight)
            logging = master and ((iter_num + 1) % cfg.log_interval == 0 or it == iters - 1)
            grads = {}
            if logging and cfg.grad_norms:  # each term's (unweighted) gradient on the shared encoder
                grads = {f"grad_{k}": grad_norm(losses[k], encoder) for k in LOSS_TERMS[1:] if k in losses}
            opt.zero_grad(set_to_none=True)
            losses["loss"].backward()
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(raw.parameters(), cfg.grad_clip)
            opt.step()
            iter_num += 1
            for k, v in losses.items():
                sums[k] = sums.get(k, 0.0) + v.item()
            n_sum += 1
            if logging:
                dt = (time.time() - t_int) / n_sum
                eta = (time.time() - t_start) / (iter_num - first_iter) * ((cfg.epochs - epoch) * iters - it - 1)
                row = {"epoch": epoch + 1, "iter": iter_num, "lr": lr, "ms_iter": round(dt * 1e3, 1),
                       "samples_s": round(cfg.batch_size / dt, 1), **{k: v / n_sum for k, v in sums.items()}, **grads}
                writer.writerow(row)
                csv_file.flush()
                terms = " ".join(f"{k} {sums[k] / n_sum:.4f}" for k in LOSS_TERMS[1:] if k in sums)
                gnorms = " grad " + " ".join(f"{k[5:]} {v:.3f}" for k, v in grads.items()) if grads else ""
                log(f"[{epoch + 1:3d}/{cfg.epochs} {it + 1:4d}/{iters}] loss {row['loss']:.4f} ({terms}){gnorms} "
                    f"lr {lr:.2e} | {dt * 1e3:.0f} ms/iter, eta {eta / 60:.1f} min")
                sums, n_sum, t_int = {}, 0, time.time()

        # end of epoch: rank 0 saves CKPT.last.pt, which --resume reads, with every rank's generators
        rng = [rng_states()] * world   # DDP: all_gather_object puts each rank's in its place
        if ddp:
            dist.all_gather_object(rng, rng_states())
        if master:
            save_atomic(checkpoint(epoch + 1, rng), last_path)
        if ddp:
            dist.barrier()
        t_int = time.time()  # saving does not count as iteration time

    if master:
        save_atomic(checkpoint(cfg.epochs), cfg.out)   # the last model, not a "best"
        csv_file.close()
        log(f"done in {(time.time() - t_start) / 60:.1f} min: {cfg.out}")
    if ddp:
        dist.destroy_process_group()
    return cfg.out


# --- validation: the fit on held-out demos ---

@torch.no_grad()
def validate(cfg):
    """Per skill of the demos' labels: arm and base MSE and grip accuracy of the action at every step (its window the
    C steps up to it), with the true skills as z (teacher forcing, as trained) and, for st and lstm, the skill module's
    argmax (as in a rollout: "_zpred" columns), and its accuracy. -> {checkpoint: {skill: {metric: value}}}"""
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    demos, meta = load_demos(cfg.data, cfg.max_demos)
    flat, starts = flatten_demos(demos, "cpu")
    ends = every_step([len(d["action"]) for d in demos], range(len(demos)))
    results = {}
    for path in cfg.validate.split(","):
        ckpt = model.load_checkpoint(path)
        check_env_config(ckpt, meta, path, cfg.data)
        net = model.model_from_checkpoint(ckpt).eval()
        per = {}  # metric -> per-step values, in the order of ends
        for i in range(0, len(ends), 512):
            b = get_batch(flat, starts, ends[i:i + 512], net.cfg.context, net.cfg.memory, net.cfg.memory_stride)
            x = net.embed_obs(b["depth"], b["state"])
            mem = {"mem": net.embed_memory(b["mem_state"]), "mem_mask": b["mem_mask"]} if net.cfg.memory else {}
            label, act = b["skill"][:, -1], b["action"][:, -1]
            z, m = {"": b["skill"]}, {}   # arm etc.: z = the true skills (or no z); arm_zpred etc.: predicted
            if net.has_skill_module:
                z["_zpred"] = net.infer_skill(x, b["mask"], **mem)[0].argmax(-1)
                m["skill_acc"] = (z["_zpred"][:, -1] == label).float()
            for name, zz in z.items():
                o = {k: v[:, -1] for k, v in net.infer_action(x, b["prev_action"], b["mask"], skill=zz,
                                                              rtg=b["rtg"], **mem).items()}
                m[f"arm{name}"] = ((o["arm"] - act[:, env.ARM]) ** 2).mean(-1)
                m[f"base{name}"] = ((o["base"] - act[:, env.BASE]) ** 2).mean(-1)
                m[f"grip_acc{name}"] = (o["grip_logits"].argmax(-1) == act[:, env.GRIP].round() + 1).float()
            for k, v in m.items():
                per.setdefault(k, []).append(v)
        per = {k: torch.cat(v) for k, v in per.items()}
        labels = flat["skill"]   # ends runs over every step of every demo, in flat's order
        table = {}
        for s in ("all", *env.SKILLS):
            sel = torch.ones_like(labels, dtype=torch.bool) if s == "all" else labels == env.SKILL_IDS[s]
            n = int(sel.sum())
            table[s] = {"steps": n, **{k: float(v[sel].mean()) if n else float("nan") for k, v in per.items()}}
        results[path] = table
        cols = [k for k in table["all"] if k != "steps"]
        print(f"\n{path} ({net.cfg.variant}) on {len(demos)} demos of {cfg.data}, {len(ends)} steps:\n"
              f"| skill | steps | {' | '.join(cols)} |\n|---|---|{'---|' * len(cols)}")
        for s, row in table.items():
            print(f"| {s} | {row['steps']} | " + " | ".join(f"{row[k]:.4f}" for k in cols) + " |")
        tmp = f"{stem(path)}.val.json.tmp{os.getpid()}"
        with open(tmp, "w") as f:
            json.dump({"data": cfg.data, "n_demos": len(demos), "per_skill": table}, f, indent=1)
        os.replace(tmp, stem(path) + ".val.json")
    return results


# --- command line ---

def parse_args(argv=None):
    """argparse generated from TrainConfig (env.add_config_args)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    return TrainConfig(**vars(env.add_config_args(p, TrainConfig).parse_args(argv)))


if __name__ == "__main__":
    args = parse_args()
    validate(args) if args.validate else train(args)
