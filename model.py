"""Skill Transformer (Huang, Batra, Rai, Szot, ICCV 2023, Sec. 4) and its baselines, in one file.

A shared encoder turns each step's depth image and state into a token x_t. Skill Inference, a
causal transformer over x_{t-C+1..t}, predicts the active skill (and, in training, which receptacle
holds the target). Action Inference, a causal transformer over the interleaved tokens
(x_t, a_{t-1}, z_t), predicts the arm and base means and a 3-way grip distribution. Training feeds
the true skills as z (teacher forcing, Sec. 4.2), except a skill_sample share of the steps, which
get the skill module's own prediction (scheduled sampling, Bengio et al. 2015), as a rollout does.
With prev_action=False (train.py's default) the a_{t-1} tokens are left out (the copycat problem,
Wen et al. 2020).

Baselines (Sec. 5.2, Sec. 5.5, Appendix C.2), chosen by ModelConfig.variant:
    st        Skill Transformer
    no_skill  action inference over (x_t, a_{t-1}) alone: no skill module, no skill tokens
    lstm      the Skill Transformer with both transformers replaced by LSTMs of similar size
    dt        Decision Transformer (Chen et al. 2021) over (R_t, x_t, a_{t-1}), R = return-to-go
    dt_skill  dt plus an auxiliary skill head trained with focal loss

Nothing here runs on its own; it is imported:
    python train.py --data data/demos --out ckpt/st.pt             # trains a model
    python -c "import model; p = model.load_policy('ckpt/st.pt')"  # p.act(obs) -> action, skill
"""
import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

import env

VARIANTS = ("st", "no_skill", "lstm", "dt", "dt_skill")
# The reach's targets (cup to object, cup to goal): normalised over whole episodes a centimetre is
# ~0.008 of a unit, too fine for the reach; ModelConfig.near_scale adds them at 10 cm scale (M9).
NEAR_FIELDS = ("obj_start", "goal")
_offsets = np.cumsum([0] + [n for _, n in env.STATE_LAYOUT])
NEAR_INDEX = [i for (name, n), o in zip(env.STATE_LAYOUT, _offsets) if name in NEAR_FIELDS for i in range(o, o + n)]


@dataclass
class ModelConfig:
    """Everything needed to rebuild the network; saved as "model_args" in every checkpoint."""
    depth_size: int = 32
    """side of the square depth image, in pixels (read from the data)"""
    state_dim: int = env.STATE_DIM
    """proprioceptive + task inputs per step (env.STATE_LAYOUT)"""
    n_skills: int = len(env.SKILLS)
    """skill classes: navigate, pick, place, open_drawer, open_fridge"""
    n_receptacles: int = len(env.RECEPTACLES) + 1
    """auxiliary receptacle classes (y^pred, Sec. 4.2): 0 = target not in a receptacle, i = in the i-th"""
    context: int = 30
    """context length C in steps (Sec. 4.1: C = 30); action inference sees 3C tokens (2C without a_{t-1})"""
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
    prev_action: bool = True
    """a_{t-1} tokens in action inference, as the paper; False leaves them out (train.py's default)"""
    skill_sample: float = 0.5
    """st/lstm, training only: probability that z_t is the skill module's own (detached) argmax
    instead of the true skill (scheduled sampling); 0: teacher forcing, as the paper (Sec. 4.2)"""


# --- observation encoders (Sec. 4.1 "Input") ---

class SmallCNN(nn.Module):
    """A 4x4 stride-4 "patchify" convolution, strided 3x3 convolutions down to about 4x4, and a
    linear layer: a fast stand-in for the paper's ResNet-18 on a CPU. Channels-last weights and
    inputs make the CPU convolutions ~3x faster (oneDNN)."""

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
        B, L, D = x.shape
        q, k, v = self.qkv(x).split(D, dim=2)
        if last_only:  # a rollout needs the last query alone; it may see every key
            q = q[:, -1:]
        q = q.view(B, q.shape[1], self.n_head, D // self.n_head).transpose(1, 2)  # (B, h, Lq, d)
        k, v = (t.view(B, L, self.n_head, D // self.n_head).transpose(1, 2) for t in (k, v))  # (B, h, L, d)
        y = F.scaled_dot_product_attention(q, k, v, is_causal=not last_only,
                                           dropout_p=self.dropout if self.training else 0.0)
        return self.resid_drop(self.proj(y.transpose(1, 2).reshape(B, q.shape[2], D)))


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
        for i, block in enumerate(self.blocks):
            # In the last layer only the last position's output is needed for a rollout step.
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
        self.cfg = cfg
        v = cfg.variant
        # Sec. 4.1: depth -> visual embedding, state -> MLP embedding, concatenated into x_t.
        self.vis = SmallCNN(cfg.depth_size, cfg.d_vis)
        d_in = cfg.state_dim + (len(NEAR_INDEX) if cfg.near_scale > 0 else 0)
        self.state_mlp = nn.Sequential(nn.Linear(d_in, cfg.d_state), nn.ReLU(),
                                       nn.Linear(cfg.d_state, cfg.d_state), nn.ReLU())
        d_tok = cfg.d_vis + cfg.d_state  # a linear map takes x_t to d_model if the sizes differ
        self.tok_proj = nn.Identity() if d_tok == cfg.d_model else nn.Linear(d_tok, cfg.d_model)
        self.pos_emb = nn.Parameter(torch.zeros(1, cfg.context, cfg.d_model))  # per-timestep, Sec. 4.1
        # Normalisation of the inputs, set by train.py from the data and saved in the state dict.
        self.register_buffer("state_mean", torch.zeros(cfg.state_dim))
        self.register_buffer("state_std", torch.ones(cfg.state_dim))
        self.register_buffer("rtg_scale", torch.ones(()))
        Backbone = LSTMBackbone if v == "lstm" else Transformer
        self.has_skill_module = v in ("st", "lstm")
        if self.has_skill_module:
            # Skill Inference (Sec. 4.1) with the auxiliary receptacle head (Sec. 4.2, Eq. 3).
            self.skill_net = Backbone(cfg)
            self.skill_head = nn.Linear(cfg.d_model, cfg.n_skills)
            self.aux_head = nn.Linear(cfg.d_model, cfg.n_receptacles)
            self.skill_emb = nn.Embedding(cfg.n_skills, cfg.d_model)  # c_t -> z_t
        if v in ("dt", "dt_skill"):
            self.rtg_emb = nn.Linear(1, cfg.d_model)
        if v == "dt_skill":
            self.skill_head = nn.Linear(cfg.d_model, cfg.n_skills)  # auxiliary skill loss (Appendix C.2)
        # Action Inference (Sec. 4.1): 12 outputs = 7 arm means, 2 base means, 3 grip logits.
        if cfg.prev_action:
            self.act_emb = nn.Linear(env.ACTION_DIM, cfg.d_model)
        self.action_net = Backbone(cfg)
        self.arm_head = nn.Linear(cfg.d_model, env.ARM.stop - env.ARM.start)
        self.base_head = nn.Linear(cfg.d_model, env.BASE.stop - env.BASE.start)
        self.grip_head = nn.Linear(cfg.d_model, len(env.GRIP_VALUES))
        self.apply(self._init_weights)

    @staticmethod
    def _init_weights(m):
        if isinstance(m, (nn.Linear, nn.Embedding)):
            nn.init.normal_(m.weight, std=0.02)
            if getattr(m, "bias", None) is not None:
                nn.init.zeros_(m.bias)

    def embed_obs(self, depth, state):
        """Token x_t. depth (B, T, 1, H, W) float in [0, 1], state (B, T, S) -> (B, T, D)."""
        B, T = state.shape[:2]
        vis = self.vis(depth.reshape(B * T, *depth.shape[2:])).view(B, T, -1)
        st = (state - self.state_mean) / self.state_std
        if self.cfg.near_scale > 0:   # the same vectors again, saturating beyond ~2 near_scale
            st = torch.cat([st, torch.tanh(state[..., NEAR_INDEX] / self.cfg.near_scale)], dim=-1)
        st = self.state_mlp(st)
        return self.tok_proj(torch.cat([vis, st], dim=-1))

    def infer_skill(self, x, mask, last_only=False):
        """Skill Inference over x (B, T, D) -> skill logits (B, T, n_skills), aux logits (B, T, M+1)
        (T = 1 with last_only: the current step alone, for a rollout).

        Left padding (mask False) becomes a zero token, exactly as in a rollout's first C steps."""
        h = self.skill_net(x * mask[..., None] + self.pos_emb[:, :x.shape[1]], last_only)
        return self.skill_head(h), self.aux_head(h)

    def infer_action(self, x, prev_action, mask, skill=None, rtg=None, last_only=False):
        """Action Inference. x (B, T, D), prev_action a_{t-1} (B, T, 10), mask (B, T) bool,
        skill z_t ids (B, T) for st/lstm, rtg (B, T) for dt -> dict of per-step outputs (B, T, .),
        or of the current step alone (B, 1, .) with last_only."""
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
        h = self.action_net(seq.view(B, T * len(toks), D), last_only)
        h = h if last_only else h.view(B, T, len(toks), D)[:, :, -1]
        out = {"arm": self.arm_head(h), "base": self.base_head(h), "grip_logits": self.grip_head(h)}
        if v == "dt_skill":
            out["skill_logits"] = self.skill_head(h)
        return out

    def forward(self, batch):
        """Training pass (Sec. 4.2): the true skills are the z_t tokens (teacher forcing), except,
        in training mode, at a random skill_sample share of the steps, where z_t is the skill
        module's own argmax at that step. It depends on x_{<=t} alone, so causality holds."""
        x = self.embed_obs(batch["depth"], batch["state"])
        out, skill = {}, batch.get("skill")
        if self.has_skill_module:
            out["skill_logits"], out["aux_logits"] = self.infer_skill(x, batch["mask"])
            if self.training and self.cfg.skill_sample > 0:   # scheduled sampling
                own = out["skill_logits"].detach().argmax(-1)                       # (B, T)
                sample = torch.rand(skill.shape, device=skill.device) < self.cfg.skill_sample
                skill = torch.where(sample, own, skill)
        out.update(self.infer_action(x, batch["prev_action"], batch["mask"], skill=skill, rtg=batch.get("rtg")))
        return out

    def compute_loss(self, out, batch, skill_weight=1.0, aux_weight=1.0):
        """Sec. 4.2: focal loss (skills, grip) + MSE (arm, base) + CE (aux), each averaged over the
        valid (unpadded) steps of the window. Returns a dict of the terms and "loss", their sum with
        the skill and aux terms weighted (the paper's unweighted sum: both weights 1)."""
        m = batch["mask"].float()
        mean = lambda l: (l * m).sum() / m.sum().clamp(min=1.0)
        act = batch["action"]
        grip_target = act[..., env.GRIP].round().long() + 1  # release/keep/grasp -> 0/1/2
        losses = {"arm": mean(((out["arm"].float() - act[..., env.ARM]) ** 2).mean(-1)),
                  "base": mean(((out["base"].float() - act[..., env.BASE]) ** 2).mean(-1)),
                  "grip": mean(focal_loss(out["grip_logits"], grip_target))}
        if "skill_logits" in out:
            losses["skill"] = mean(focal_loss(out["skill_logits"], batch["skill"]))  # Eq. 1
        if "aux_logits" in out:
            aux = F.cross_entropy(out["aux_logits"].float().flatten(0, 1), batch["receptacle"].flatten(),
                                  reduction="none").view_as(m)
            losses["aux"] = mean(aux)  # Eq. 3
        weight = {"skill": skill_weight, "aux": aux_weight}
        losses["loss"] = sum(weight.get(k, 1.0) * v for k, v in losses.items())
        return losses

    def encoder_parameters(self):
        """The shared observation encoder's parameters (CNN, state MLP, token projection): what
        both modules read, where train.py measures each loss term's gradient."""
        return [p for m in (self.vis, self.state_mlp, self.tok_proj) for p in m.parameters()]

    def num_params(self):
        return sum(p.numel() for p in self.parameters())


def focal_loss(logits, target, gamma=2.0):
    """Focal loss (Lin et al. 2017), per element: -(1 - p_y)^gamma log p_y. It counters the skill
    imbalance (navigate dominates, Sec. 4.2). logits (..., K), target (...) -> (...)."""
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
        raise ValueError(f"{path}: not a Skill Transformer checkpoint (missing {missing}); "
                         "expected the dict that train.py writes")
    return ckpt


def model_from_checkpoint(ckpt, device="cpu"):
    """Rebuild the network from ckpt["model_args"] and load its weights."""
    try:
        cfg = ModelConfig(**ckpt["model_args"])
    except TypeError as e:
        raise ValueError(f"checkpoint model_args do not match ModelConfig ({e}): it was written by an "
                         "older version of model.py; retrain it") from e
    m = SkillTransformer(cfg)
    m.load_state_dict(ckpt["model"])
    return m.to(device)


class Policy:
    """Acts in the env from raw observations, keeping the last C steps (Sec. 4.1, test time).

    Per step only the new observation is encoded (past tokens are cached in a rolling, left-padded
    window); the transformers run over the window with the *predicted* skills as z, the last layer
    for the current step only. With batch=B it acts for B episodes at once (evaluate.py)."""

    def __init__(self, model, env_config, rtg_max, device="cpu", batch=1):
        if model.cfg.state_dim != env.STATE_DIM:
            raise ValueError(f"checkpoint expects {model.cfg.state_dim} state inputs, env.STATE_LAYOUT gives "
                             f"{env.STATE_DIM}: it was trained on an older observation; retrain it")
        self.model = model.eval()
        self.cfg = model.cfg
        self.variant = self.cfg.variant
        self.env_config = dict(env_config)
        self.rtg_max = float(rtg_max)
        self.device = torch.device(device)
        self.batch = batch
        self.reset()

    def reset(self):
        B, C, dev = self.batch, self.cfg.context, self.device
        self.x = torch.zeros(B, C, self.cfg.d_model, device=dev)           # x_t
        self.prev_action = torch.zeros(B, C, env.ACTION_DIM, device=dev)   # a_{t-1}
        self.skill = torch.zeros(B, C, dtype=torch.long, device=dev)       # predicted z_t
        self.rtg = torch.zeros(B, C, device=dev)                           # R_t (dt variants)
        self.mask = torch.zeros(B, C, dtype=torch.bool, device=dev)        # False = padding
        self.last_action = torch.zeros(B, env.ACTION_DIM, device=dev)
        self.return_to_go = torch.full((B,), self.rtg_max, device=dev)  # Appendix C.2: the max return of the demos
        self.t = 0

    def act(self, obs, reward=0.0):
        """obs: the env's observation dict; reward: the reward of the previous step (dt only).
        Returns (action float32 (10,), predicted skill id, -1 where the variant predicts none)."""
        actions, skills = self.act_batch([obs], [reward])
        return actions[0], skills[0]

    @torch.inference_mode()
    def act_batch(self, obs, rewards):
        """One step of each of the B episodes: obs and rewards are lists of B -> (actions (B, 10)
        float32, list of B skill ids)."""
        S, B = self.cfg.depth_size, self.batch
        if len(obs) != B:
            raise ValueError(f"got {len(obs)} observations for a policy of batch {B}")
        depth = np.stack([env.depth_to_uint8(o["depth"]) for o in obs])  # quantised as the demos are
        if depth.shape[1:] != (S, S):
            raise ValueError(f"depth image is {depth.shape[1:]}, the model was trained on ({S}, {S})")
        if self.t > 0:
            self.return_to_go -= torch.as_tensor(rewards, dtype=torch.float32, device=self.device)
        d = torch.from_numpy(depth).to(self.device, torch.float32).div_(255.0).view(B, 1, 1, S, S)
        s = torch.from_numpy(np.stack([env.state_vector(o) for o in obs])).to(self.device).view(B, 1, -1)
        for name in ("x", "prev_action", "skill", "rtg", "mask"):  # slide the window by one step
            setattr(self, name, torch.roll(getattr(self, name), -1, dims=1))
        self.x[:, -1] = self.model.embed_obs(d, s)[:, 0]
        self.prev_action[:, -1] = self.last_action
        self.rtg[:, -1] = self.return_to_go
        self.mask[:, -1] = True
        skills = torch.full((B,), -1)
        if self.model.has_skill_module:
            skill_logits, _ = self.model.infer_skill(self.x, self.mask, last_only=True)
            skills = skill_logits[:, -1].argmax(-1)
            self.skill[:, -1] = skills
        out = self.model.infer_action(self.x, self.prev_action, self.mask, skill=self.skill, rtg=self.rtg,
                                      last_only=True)
        if "skill_logits" in out:
            skills = out["skill_logits"][:, -1].argmax(-1)
        grip = out["arm"].new_tensor(env.GRIP_VALUES)[out["grip_logits"][:, -1].argmax(-1)]
        # ARM, BASE, GRIP are action[0:7], [7:9], [9]; means clipped to the action box
        action = torch.cat([out["arm"][:, -1], out["base"][:, -1], grip[:, None]], dim=1).clamp(-1, 1)
        self.last_action = action
        self.t += 1
        return action.cpu().numpy().astype(np.float32), skills.tolist()


def load_policy(path, device="cpu", batch=1):
    """Checkpoint written by train.py -> Policy with reset(), act(obs, reward) and act_batch."""
    ckpt = load_checkpoint(path, device)
    policy = Policy(model_from_checkpoint(ckpt, device), ckpt["env_config"], ckpt["rtg_max"], device, batch)
    # How it was trained (train.Config, demos used), for evaluate.py's grouping of the Fig. 3 runs.
    policy.train_config = dict(ckpt.get("config", {}), n_demos=ckpt.get("n_demos"))
    return policy
