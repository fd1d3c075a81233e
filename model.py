"""Skill Transformer (Huang, Batra, Rai, Szot, ICCV 2023, Sec. 4) and its baselines, in one file.

A shared encoder turns each step's depth image and state into a token x_t. Skill Inference, a causal transformer over
x_{t-C+1..t}, predicts the active skill (in training also which receptacle holds the target and how open the target's
and the goal's receptacles are). Action Inference, a causal transformer over the interleaved tokens (x_t, a_{t-1},
z_t), predicts arm and base means and 3 grip logits. Training feeds the true skills as z (teacher forcing, Sec. 4.2)
but, at a skill_sample share of the steps, the skill module's own prediction, as a rollout does (scheduled sampling,
Bengio et al. 2015). prev_action=False (default) leaves out the a_{t-1} tokens (the copycat problem, Wen et al. 2020).

Memory (not in the paper): both transformers also read `memory` older steps, one every `memory_stride` steps before
the window, as state-only tokens (where the robot was, what it held): a goal receptacle opened 200 steps before the
pick is out of view and of a 15-step window, yet the expert's next choice rests on it (EXPERIMENTS.md R33, R48).

Baselines (Sec. 5.2, Sec. 5.5, Appendix C.2), chosen by ModelConfig.variant:
    st        Skill Transformer
    no_skill  action inference over (x_t, a_{t-1}) alone: no skill module, no skill tokens
    lstm      the Skill Transformer with both transformers replaced by LSTMs of similar size
    dt        Decision Transformer (Chen et al. 2021) over (R_t, x_t, a_{t-1}), R = return-to-go
    dt_skill  dt plus an auxiliary skill head trained with focal loss

Needs torch and numpy only, so it can be copied elsewhere; a rollout reads its observation layout from the checkpoint.

    python model.py                                                  # self-check: sizes, a loss
    python -c "import model; p = model.load_policy('pretrained/st.pt')"   # p.act(obs) -> action, skill
"""
import os
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

VARIANTS = ("st", "no_skill", "lstm", "dt", "dt_skill")
# The action layout of env.py, repeated so that this file stands alone (test_all.py checks both agree).
ACTION_DIM = 10                                      # 7 arm deltas, 2 base velocities, 1 grip
ARM, BASE, GRIP = slice(0, 7), slice(7, 9), 9
GRIP_VALUES = (-1.0, 0.0, 1.0)                       # release, keep, grasp = grip classes 0, 1, 2
# env.STATE_LAYOUT with obs="paper": the default input layout; train.py passes the data's own.
PAPER_STATE = (("joint", 7), ("joint_target", 7), ("is_holding", 1), ("ee_rest", 3), ("obj_start", 3),
               ("goal", 3), ("obj_start_polar", 3), ("goal_polar", 3))
# The reach's targets (cup to object, cup to goal): normalised over whole episodes a centimetre is ~0.008 of a unit,
# too fine for the reach; ModelConfig.near_scale adds them at 10 cm scale (M9).
NEAR_FIELDS = ("obj_start", "goal")
NET_BATCH = 8   # Policy runs the network on this many rows, padded: see Policy


@dataclass
class ModelConfig:
    """Everything needed to rebuild the network, saved as "model_args" in each checkpoint; defaults: README, Results."""
    depth_size: int = 32
    """side of the square depth image, in pixels (read from the data)"""
    state_layout: tuple = PAPER_STATE
    """((name, size), ...) of the state vector (the data's meta.json; env.state_layout(obs))"""
    n_skills: int = 5
    """skill classes: navigate, pick, place, open_drawer, open_fridge (env.SKILLS)"""
    n_receptacles: int = 4
    """auxiliary receptacle classes (y^pred, Sec. 4.2): 0 = target not in a receptacle, i = in the i-th"""
    context: int = 15
    """context length C in steps (Sec. 4.1: C = 30; 15 solved more here, EXPERIMENTS.md R20)"""
    memory: int = 12
    """older steps read as state-only tokens before the window (0: none, as the paper)"""
    memory_stride: int = 40
    """steps between memory tokens: they reach memory x memory_stride steps before the window"""
    d_vis: int = 64
    """visual embedding size (paper: 256)"""
    d_state: int = 64
    """state embedding size (paper: 256)"""
    near_scale: float = 0.1
    """metres: > 0 also feeds tanh(v / near_scale) of the NEAR_FIELDS vectors to the state MLP; 0: off"""
    d_model: int = 128
    """transformer width (paper: 512; 128 keeps a rollout step under 5 ms on one CPU core)"""
    n_layer: int = 2
    """layers per transformer (Sec. 4.1: 2)"""
    n_head: int = 4
    """attention heads"""
    dropout: float = 0.0
    """dropout in the transformer blocks (the Decision Transformer used 0.1)"""
    variant: str = "st"
    """st, no_skill, lstm, dt or dt_skill"""
    prev_action: bool = False
    """the paper's a_{t-1} tokens in action inference; off: with them the policy copies a_{t-1}"""
    skill_sample: float = 0.5
    """st/lstm, training only: probability that z_t is the skill module's own (detached) argmax instead of the true
    skill (scheduled sampling); 0: teacher forcing, as the paper (Sec. 4.2)"""

    @property
    def state_dim(self):
        return sum(n for _, n in self.state_layout)

    @property
    def near_index(self):
        """Positions of the NEAR_FIELDS numbers in the state vector."""
        offsets = np.cumsum([0] + [n for _, n in self.state_layout])
        return [i for (name, n), o in zip(self.state_layout, offsets) if name in NEAR_FIELDS for i in range(o, o + n)]


# --- observation encoders (Sec. 4.1 "Input") ---

class SmallCNN(nn.Module):
    """A 4x4 stride-4 "patchify" convolution, strided 3x3 convolutions down to about 4x4 and a linear layer: a fast CPU
    stand-in for the paper's ResNet-18. Channels-last weights and inputs make CPU convolutions ~3x faster (oneDNN)."""

    def __init__(self, size, out_dim):
        super().__init__()
        layers, ch, s = [nn.Conv2d(1, 32, 4, stride=4), nn.ReLU()], 32, size // 4
        while s >= 8:
            layers += [nn.Conv2d(ch, min(2 * ch, 64), 3, stride=2, padding=1), nn.ReLU()]
            ch, s = min(2 * ch, 64), (s + 1) // 2
        self.convs = nn.Sequential(*layers).to(memory_format=torch.channels_last)
        self.fc = nn.Linear(ch * s * s, out_dim)

    def forward(self, x):  # (N, 1, H, W) -> (N, out_dim)
        h = self.convs(x.contiguous(memory_format=torch.channels_last))
        return F.relu(self.fc(h.flatten(1)))


# --- sequence backbones (nanoGPT blocks; an LSTM for the lstm baseline) ---

class CausalSelfAttention(nn.Module):
    def __init__(self, cfg):
        super().__init__()
        self.n_head = cfg.n_head
        self.qkv = nn.Linear(cfg.d_model, 3 * cfg.d_model)
        self.proj = nn.Linear(cfg.d_model, cfg.d_model)
        self.dropout = cfg.dropout
        self.resid_drop = nn.Dropout(cfg.dropout)

    def forward(self, x, last_only=False):
        B, _, D = x.shape
        q, k, v = self.qkv(x).split(D, dim=2)
        if last_only:  # a rollout needs the last query alone; it may see every key
            q = q[:, -1:]
        q, k, v = (t.view(B, -1, self.n_head, D // self.n_head).transpose(1, 2) for t in (q, k, v))  # (B, h, L or 1, d)
        y = F.scaled_dot_product_attention(q, k, v, is_causal=not last_only,
                                           dropout_p=self.dropout if self.training else 0.0)
        return self.resid_drop(self.proj(y.transpose(1, 2).reshape(B, -1, D)))


class Block(nn.Module):
    def __init__(self, cfg):
        super().__init__()
        self.ln1 = nn.LayerNorm(cfg.d_model)
        self.attn = CausalSelfAttention(cfg)
        self.ln2 = nn.LayerNorm(cfg.d_model)
        self.mlp = nn.Sequential(nn.Linear(cfg.d_model, 4 * cfg.d_model), nn.ReLU(),
                                 nn.Linear(4 * cfg.d_model, cfg.d_model), nn.Dropout(cfg.dropout))

    def forward(self, x, last_only=False):
        x = (x[:, -1:] if last_only else x) + self.attn(self.ln1(x), last_only)
        return x + self.mlp(self.ln2(x))


class Transformer(nn.Module):
    """Causal transformer (Sec. 4.1): token i attends to tokens <= i only."""

    def __init__(self, cfg):
        super().__init__()
        self.drop = nn.Dropout(cfg.dropout)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layer))
        self.ln_f = nn.LayerNorm(cfg.d_model)

    def forward(self, x, last_only=False):  # (B, L, D) -> (B, L, D), or (B, 1, D) if last_only
        x = self.drop(x)
        for i, block in enumerate(self.blocks):   # a rollout step needs the last layer's last position alone
            x = block(x, last_only and i == len(self.blocks) - 1)
        return self.ln_f(x)


class LSTMBackbone(nn.Module):
    """The lstm baseline (Sec. 5.5): same tokens, an LSTM in place of the transformer."""

    def __init__(self, cfg):
        super().__init__()
        self.lstm = nn.LSTM(cfg.d_model, cfg.d_model, num_layers=cfg.n_layer, batch_first=True,
                            dropout=cfg.dropout if cfg.n_layer > 1 else 0.0)
        self.ln_f = nn.LayerNorm(cfg.d_model)

    def forward(self, x, last_only=False):  # (B, L, D) -> (B, L, D), causal by construction
        h = self.lstm(x)[0]
        return self.ln_f(h[:, -1:] if last_only else h)


# --- the policy network ---

class SkillTransformer(nn.Module):
    """Observation encoder + Skill Inference + Action Inference (Fig. 2), or a baseline."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        if cfg.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {cfg.variant!r}")
        if not 0 <= cfg.skill_sample <= 1:
            raise ValueError(f"skill_sample must lie in [0, 1], got {cfg.skill_sample}")
        if cfg.d_model % cfg.n_head:
            raise ValueError(f"d_model ({cfg.d_model}) must be divisible by n_head ({cfg.n_head})")
        if cfg.memory < 0 or (cfg.memory and cfg.memory_stride < 1):
            raise ValueError(f"memory must be >= 0 and memory_stride >= 1, got {cfg.memory}, {cfg.memory_stride}")
        self.cfg, v = cfg, cfg.variant
        self.near_index = cfg.near_index
        # Sec. 4.1: depth -> visual embedding, state -> MLP embedding, concatenated into x_t.
        self.vis = SmallCNN(cfg.depth_size, cfg.d_vis)
        d_in = cfg.state_dim + (len(self.near_index) if cfg.near_scale > 0 else 0)
        self.state_mlp = nn.Sequential(nn.Linear(d_in, cfg.d_state), nn.ReLU(),
                                       nn.Linear(cfg.d_state, cfg.d_state), nn.ReLU())
        d_tok = cfg.d_vis + cfg.d_state  # a linear map takes x_t to d_model if the sizes differ
        self.tok_proj = nn.Identity() if d_tok == cfg.d_model else nn.Linear(d_tok, cfg.d_model)
        self.pos_emb = nn.Parameter(torch.zeros(1, cfg.context, cfg.d_model))  # per-timestep, Sec. 4.1
        if cfg.memory:   # memory tokens: the state embedding of older steps, a position each
            self.mem_proj = nn.Linear(cfg.d_state, cfg.d_model)
            self.mem_pos = nn.Parameter(torch.zeros(1, cfg.memory, cfg.d_model))
        # Normalisation of the inputs, set by train.py from the data and saved in the state dict.
        self.register_buffer("state_mean", torch.zeros(cfg.state_dim))
        self.register_buffer("state_std", torch.ones(cfg.state_dim))
        self.register_buffer("rtg_scale", torch.ones(()))
        Backbone = LSTMBackbone if v == "lstm" else Transformer
        self.has_skill_module = v in ("st", "lstm")
        if self.has_skill_module:
            # Skill Inference (Sec. 4.1) + aux heads (Sec. 4.2, Eq. 3): target's receptacle, its and the goal's openness
            self.skill_net = Backbone(cfg)
            self.skill_head = nn.Linear(cfg.d_model, cfg.n_skills)
            self.aux_head = nn.Linear(cfg.d_model, cfg.n_receptacles)
            self.open_head = nn.Linear(cfg.d_model, 2)
            self.skill_emb = nn.Embedding(cfg.n_skills, cfg.d_model)  # c_t -> z_t
        if v in ("dt", "dt_skill"):
            self.rtg_emb = nn.Linear(1, cfg.d_model)
        if v == "dt_skill":
            self.skill_head = nn.Linear(cfg.d_model, cfg.n_skills)  # auxiliary skill loss (Appendix C.2)
        # Action Inference (Sec. 4.1): 12 outputs = 7 arm means, 2 base means, 3 grip logits.
        if cfg.prev_action:
            self.act_emb = nn.Linear(ACTION_DIM, cfg.d_model)
        self.action_net = Backbone(cfg)
        self.arm_head = nn.Linear(cfg.d_model, ARM.stop - ARM.start)
        self.base_head = nn.Linear(cfg.d_model, BASE.stop - BASE.start)
        self.grip_head = nn.Linear(cfg.d_model, len(GRIP_VALUES))
        for m in self.modules():
            if isinstance(m, (nn.Linear, nn.Embedding)):
                nn.init.normal_(m.weight, std=0.02)
                if getattr(m, "bias", None) is not None:
                    nn.init.zeros_(m.bias)

    def embed_state(self, state):
        """state (..., S) -> the state MLP's embedding (..., d_state)."""
        st = (state - self.state_mean) / self.state_std
        if self.cfg.near_scale > 0:   # the reach's vectors again, saturating beyond ~2 near_scale
            st = torch.cat([st, torch.tanh(state[..., self.near_index] / self.cfg.near_scale)], dim=-1)
        return self.state_mlp(st)

    def embed_obs(self, depth, state):
        """Token x_t. depth (B, T, 1, H, W) float in [0, 1], state (B, T, S) -> (B, T, D)."""
        B, T = state.shape[:2]
        vis = self.vis(depth.reshape(B * T, *depth.shape[2:])).view(B, T, -1)
        return self.tok_proj(torch.cat([vis, self.embed_state(state)], dim=-1))

    def embed_memory(self, state):
        """Memory tokens: states of older steps (B, M, S) -> (B, M, D), or None without memory."""
        return self.mem_proj(self.embed_state(state)) if self.cfg.memory else None

    def _run(self, net, seq, mem, mem_mask, last_only):
        """A backbone over the memory tokens (masked like padding, each with its position) then seq."""
        M = self.cfg.memory
        if M:
            seq = torch.cat([mem * mem_mask[..., None] + self.mem_pos, seq], dim=1)
        h = net(seq, last_only)
        return h if last_only or not M else h[:, M:]

    def infer_skill(self, x, mask, mem=None, mem_mask=None, last_only=False):
        """Skill Inference over x (B, T, D) and memory tokens mem (B, M, D) -> skill logits (B, T, n_skills), aux
        logits (B, T, M+1), open logits (B, T, 2); T = 1 with last_only (the current step alone, for a rollout).
        Left padding (mask False) becomes a zero token, exactly as in a rollout's first C steps."""
        h = self._run(self.skill_net, x * mask[..., None] + self.pos_emb[:, :x.shape[1]], mem, mem_mask, last_only)
        return self.skill_head(h), self.aux_head(h), self.open_head(h)

    def infer_action(self, x, prev_action, mask, skill=None, rtg=None, mem=None, mem_mask=None, last_only=False):
        """Action Inference. x (B, T, D), prev_action a_{t-1} (B, T, 10), mask (B, T) bool, skill z_t ids (B, T) for
        st/lstm, rtg (B, T) for dt, memory tokens (B, M, D) -> dict of per-step outputs (B, T, .), or of the current
        step alone (B, 1, .) with last_only."""
        v, (B, T, D) = self.cfg.variant, x.shape
        a = (self.act_emb(prev_action),) if self.cfg.prev_action else ()  # without it: (x_t, z_t) etc.
        if v in ("st", "lstm"):
            toks = (x, *a, self.skill_emb(skill))  # (x_t, a_{t-1}, z_t), Sec. 4.1
        elif v == "no_skill":
            toks = (x, *a)
        else:
            toks = (self.rtg_emb((rtg / self.rtg_scale)[..., None]), x, *a)  # (R_t, x_t, a_{t-1}), DT
        pos = self.pos_emb[:, :T]
        seq = torch.stack([t * mask[..., None] + pos for t in toks], dim=2)  # (B, T, k, D)
        # The last token of step t has seen x_{<=t}, a_{<=t-1} (and z_{<=t}): it predicts a_t.
        h = self._run(self.action_net, seq.view(B, T * len(toks), D), mem, mem_mask, last_only)
        h = h if last_only else h.view(B, T, len(toks), D)[:, :, -1]
        out = {"arm": self.arm_head(h), "base": self.base_head(h), "grip_logits": self.grip_head(h)}
        if v == "dt_skill":
            out["skill_logits"] = self.skill_head(h)
        return out

    def forward(self, batch):
        """Training pass (Sec. 4.2): z_t = the true skills (teacher forcing) except, in training mode, at a random
        skill_sample share of the steps: there the skill module's own argmax, which depends on x_{<=t} only (causal)."""
        x = self.embed_obs(batch["depth"], batch["state"])
        mem, mem_mask = (self.embed_memory(batch["mem_state"]), batch["mem_mask"]) if self.cfg.memory else (None, None)
        out, skill = {}, batch.get("skill")
        if self.has_skill_module:
            out["skill_logits"], out["aux_logits"], out["open_logits"] = self.infer_skill(x, batch["mask"], mem, mem_mask)
            if self.training and self.cfg.skill_sample > 0:   # scheduled sampling
                own = out["skill_logits"].detach().argmax(-1)                       # (B, T)
                sample = torch.rand(skill.shape, device=skill.device) < self.cfg.skill_sample
                skill = torch.where(sample, own, skill)
        out.update(self.infer_action(x, batch["prev_action"], batch["mask"], skill=skill, rtg=batch.get("rtg"),
                                     mem=mem, mem_mask=mem_mask))
        return out

    def compute_loss(self, out, batch, skill_weight=1.0, aux_weight=1.0, open_weight=1.0):
        """Sec. 4.2: focal loss (skills, grip) + MSE (arm, base) + CE (aux) + BCE (open), each averaged over the valid
        (unpadded) steps -> dict of the terms and "loss", their sum with skill, aux, open weighted (1: the paper's)."""
        m = batch["mask"].float()
        mean = lambda l: (l * m).sum() / m.sum().clamp(min=1.0)
        act = batch["action"]
        grip_target = act[..., GRIP].round().long() + 1  # release/keep/grasp -> 0/1/2
        losses = {"arm": mean(((out["arm"].float() - act[..., ARM]) ** 2).mean(-1)),
                  "base": mean(((out["base"].float() - act[..., BASE]) ** 2).mean(-1)),
                  "grip": mean(focal_loss(out["grip_logits"], grip_target))}
        if "skill_logits" in out:
            losses["skill"] = mean(focal_loss(out["skill_logits"], batch["skill"]))  # Eq. 1
        if "aux_logits" in out:   # Eq. 3; then how open each receptacle is, a fraction in [0, 1]: soft targets
            aux = F.cross_entropy(out["aux_logits"].float().flatten(0, 1), batch["receptacle"].flatten(),
                                  reduction="none").view_as(m)
            losses["aux"] = mean(aux)
            bce = F.binary_cross_entropy_with_logits(out["open_logits"].float(), batch["receptacle_open"],
                                                     reduction="none")
            losses["open"] = mean(bce.mean(-1))
        weight = {"skill": skill_weight, "aux": aux_weight, "open": open_weight}
        losses["loss"] = sum(weight.get(k, 1.0) * v for k, v in losses.items())
        return losses

    def num_params(self):
        return sum(p.numel() for p in self.parameters())


def focal_loss(logits, target, gamma=2.0):
    """Focal loss (Lin et al. 2017), per element: -(1 - p_y)^gamma log p_y. It counters the skill imbalance (navigate
    dominates, Sec. 4.2). logits (..., K), target (...) -> (...)."""
    logp = F.log_softmax(logits.float(), dim=-1).gather(-1, target[..., None]).squeeze(-1)
    return -((1.0 - logp.exp()) ** gamma) * logp


# --- rollout policy built from a checkpoint ---

def load_checkpoint(path, device="cpu"):
    """torch.load(weights_only=True) with clear errors for a missing file or a foreign format."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)
    except Exception as e:
        raise ValueError(f"{path}: not a readable torch checkpoint ({type(e).__name__}: {e})") from e
    needed = ("model", "model_args", "env_config", "rtg_max")
    missing = [k for k in needed if not isinstance(ckpt, dict) or k not in ckpt]
    if missing:
        raise ValueError(f"{path}: not a Skill Transformer checkpoint (missing {missing}); expected train.py's dict")
    if "obs" not in ckpt["env_config"] or "state_layout" not in ckpt["model_args"]:
        raise ValueError(f"{path}: written before observation modes (env.EnvConfig.obs) existed; retrain it")
    return ckpt


def model_from_checkpoint(ckpt, device="cpu"):
    """Rebuild the network from ckpt["model_args"] and load its weights."""
    try:
        cfg = ModelConfig(**ckpt["model_args"])
    except TypeError as e:
        raise ValueError(f"checkpoint model_args do not match ModelConfig ({e}): older model.py; retrain it") from e
    m = SkillTransformer(cfg)
    m.load_state_dict(ckpt["model"])
    return m.to(device)


class Policy:
    """Acts in the env from raw observations, keeping the last C steps and the memory's older states (Sec. 4.1, test
    time). Each step encodes only the new observation (past tokens wait in a rolling, left-padded window) and runs the
    transformers over the window with the *predicted* skills as z, the last layer for the current step only. batch=B
    acts for B episodes at once (evaluate.py). The network always runs on NET_BATCH rows, padded: CPU matrix kernels
    round differently per batch size, and an episode's actions must not depend on how many episodes share the call."""

    def __init__(self, model, env_config, rtg_max, device="cpu", batch=1):
        self.model = model.eval()
        self.cfg = model.cfg
        self.variant = self.cfg.variant
        self.env_config = dict(env_config)
        self.layout = tuple(tuple(f) for f in self.cfg.state_layout)
        self.rtg_max = float(rtg_max)
        self.device = torch.device(device)
        self.batch = batch
        self.reset()

    def reset(self):
        B, C, dev = -(-self.batch // NET_BATCH) * NET_BATCH, self.cfg.context, self.device   # rows, padded
        H = C + self.cfg.memory * self.cfg.memory_stride                    # steps of state kept
        self.x = torch.zeros(B, C, self.cfg.d_model, device=dev)           # x_t
        self.prev_action = torch.zeros(B, C, ACTION_DIM, device=dev)       # a_{t-1}
        self.skill = torch.zeros(B, C, dtype=torch.long, device=dev)       # predicted z_t
        self.rtg = torch.zeros(B, C, device=dev)                           # R_t (dt variants)
        self.mask = torch.zeros(B, C, dtype=torch.bool, device=dev)        # False = padding
        self.states = torch.zeros(B, H, self.cfg.state_dim, device=dev)    # raw states, for the memory
        self.states_mask = torch.zeros(B, H, dtype=torch.bool, device=dev)
        self.last_action = torch.zeros(B, ACTION_DIM, device=dev)
        self.return_to_go = torch.full((B,), self.rtg_max, device=dev)  # Appendix C.2: the max return of the demos
        self.t = 0

    def act(self, obs, reward=0.0):
        """obs: the env's observation dict; reward: the reward of the previous step (dt only).
        Returns (action float32 (10,), predicted skill id, -1 where the variant predicts none)."""
        actions, skills = self.act_batch([obs], [reward])
        return actions[0], skills[0]

    def _check(self, obs):
        names = {name for name, _ in self.layout}
        missing, extra = names - set(obs), (set(obs) - names - {"depth"}) & {"receptacle_open"}
        if missing or extra:
            mode = self.env_config.get("obs")
            other = "privileged" if mode == "paper" else "paper"
            raise ValueError(f"the policy was trained with obs={mode!r}, the observation has "
                             f"{'no ' + str(sorted(missing)) if missing else sorted(extra)}: it comes from an "
                             f"obs={other!r} env; build the env with the policy's env_config")

    def _state(self, o):
        return np.concatenate([np.asarray(o[k], np.float32).reshape(n) for k, n in self.layout])

    @torch.inference_mode()
    def act_batch(self, obs, rewards):
        """One step of each of B episodes: obs, rewards lists of B -> (actions (B, 10) float32, list of B skill ids)."""
        S, B, cfg = self.cfg.depth_size, self.batch, self.cfg
        if len(obs) != B:
            raise ValueError(f"got {len(obs)} observations for a policy of batch {B}")
        self._check(obs[0])
        # quantised as the demos are (env.depth_to_uint8)
        depth = np.stack([np.round(np.clip(o["depth"][..., 0], 0.0, 1.0) * 255.0).astype(np.uint8) for o in obs])
        if depth.shape[1:] != (S, S):
            raise ValueError(f"depth image is {depth.shape[1:]}, the model was trained on ({S}, {S})")
        P = self.x.shape[0]                  # rows, padded to a multiple of NET_BATCH
        pad = lambda a: np.concatenate([a, np.zeros((P - B, *a.shape[1:]), a.dtype)])
        if self.t > 0:
            self.return_to_go[:B] -= torch.as_tensor(rewards, dtype=torch.float32, device=self.device)
        d = torch.from_numpy(pad(depth)).to(self.device, torch.float32).div_(255.0).view(P, 1, 1, S, S)
        s = torch.from_numpy(pad(np.stack([self._state(o) for o in obs]))).to(self.device).view(P, 1, -1)
        for name in ("x", "prev_action", "skill", "rtg", "mask", "states", "states_mask"):  # slide by one step
            setattr(self, name, torch.roll(getattr(self, name), -1, dims=1))
        self.states[:, -1], self.states_mask[:, -1] = s[:, 0], True
        self.prev_action[:, -1], self.rtg[:, -1], self.mask[:, -1] = self.last_action, self.return_to_go, True
        # memory step j (1..M) lies j * stride steps before the window's first step; oldest first
        mem_at = [self.states.shape[1] - cfg.context - j * cfg.memory_stride for j in range(cfg.memory, 0, -1)]
        skills, actions = torch.full((P,), -1), torch.zeros(P, ACTION_DIM, device=self.device)
        for r in range(0, P, NET_BATCH):
            rows = slice(r, r + NET_BATCH)
            self.x[rows, -1] = self.model.embed_obs(d[rows], s[rows])[:, 0]
            mem = self.model.embed_memory(self.states[rows][:, mem_at])
            mem_mask = self.states_mask[rows][:, mem_at]
            if self.model.has_skill_module:
                logits = self.model.infer_skill(self.x[rows], self.mask[rows], mem, mem_mask, last_only=True)[0]
                skills[rows] = logits[:, -1].argmax(-1)
                self.skill[rows, -1] = skills[rows]
            out = self.model.infer_action(self.x[rows], self.prev_action[rows], self.mask[rows], skill=self.skill[rows],
                                          rtg=self.rtg[rows], mem=mem, mem_mask=mem_mask, last_only=True)
            if "skill_logits" in out:
                skills[rows] = out["skill_logits"][:, -1].argmax(-1)
            grip = out["arm"].new_tensor(GRIP_VALUES)[out["grip_logits"][:, -1].argmax(-1)]
            # ARM, BASE, GRIP are action[0:7], [7:9], [9]; means clipped to the action box
            actions[rows] = torch.cat([out["arm"][:, -1], out["base"][:, -1], grip[:, None]], dim=1).clamp(-1, 1)
        self.last_action = actions
        self.t += 1
        return actions[:B].cpu().numpy().astype(np.float32), skills[:B].tolist()


def load_policy(path, device="cpu", batch=1):
    """Checkpoint written by train.py -> Policy with reset(), act(obs, reward) and act_batch."""
    ckpt = load_checkpoint(path, device)
    policy = Policy(model_from_checkpoint(ckpt, device), ckpt["env_config"], ckpt["rtg_max"], device, batch)
    # How it was trained (train.Config, demos used), for evaluate.py's grouping of the Fig. 3 runs.
    policy.train_config = dict(ckpt.get("config", {}), n_demos=ckpt.get("n_demos"))
    return policy


# --- self-check: python model.py ---

def random_batch(cfg, B=2, seed=0):
    """A training batch of random inputs for a config (the keys train.get_batch produces)."""
    g = torch.Generator().manual_seed(seed)
    T, S, M = cfg.context, cfg.depth_size, cfg.memory
    action = torch.rand(B, T, ACTION_DIM, generator=g) * 2 - 1
    action[..., GRIP] = torch.randint(-1, 2, (B, T), generator=g).float()
    return {"depth": torch.rand(B, T, 1, S, S, generator=g), "state": torch.randn(B, T, cfg.state_dim, generator=g),
            "prev_action": torch.rand(B, T, ACTION_DIM, generator=g) * 2 - 1, "action": action,
            "skill": torch.randint(0, cfg.n_skills, (B, T), generator=g),
            "receptacle": torch.randint(0, cfg.n_receptacles, (B, T), generator=g),
            "receptacle_open": torch.rand(B, T, 2, generator=g), "rtg": torch.randn(B, T, generator=g),
            "mask": torch.ones(B, T, dtype=torch.bool), "mem_state": torch.randn(B, M, cfg.state_dim, generator=g),
            "mem_mask": torch.ones(B, M, dtype=torch.bool)}


if __name__ == "__main__":
    torch.manual_seed(0)
    print(f"ModelConfig(): {asdict(ModelConfig())}")
    for variant in VARIANTS:
        cfg = ModelConfig(variant=variant)
        net = SkillTransformer(cfg)
        batch = random_batch(cfg)
        losses = net.compute_loss(net(batch), batch, skill_weight=0.3, aux_weight=0.1, open_weight=0.1)
        assert torch.isfinite(losses["loss"]), losses
        terms = ", ".join(f"{k} {v.item():.3f}" for k, v in losses.items() if k != "loss")
        print(f"{variant:9s} {net.num_params() / 1e6:.2f} M parameters; random batch: loss {losses['loss'].item():.3f} ({terms})")
