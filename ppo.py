"""Mono: the monolithic reinforcement-learning baseline of Table 1 (Sec. 5.2, Appendix C), by PPO.

One policy maps the observation to the whole-body action and learns from the env's dense reward
alone, no demonstrations (the paper's Mono: DD-PPO, 100 M steps, 21 hours on 4 GPUs, 0 % success).
The actor is the `no_skill` network of model.py with a context of one step (the same observation
encoder: depth CNN + state MLP), so its checkpoint is read by `evaluate.py --policy` like any other;
PPO adds a learned log-std for the arm and base means, and a value head on the encoder's token.
The algorithm follows CleanRL's `ppo_continuous_action.py` (Schulman et al. 2017: clipped ratio,
GAE, minibatch epochs), with the grip as a categorical over release, keep, grasp.

    python ppo.py --steps 800000 --out ckpt/mono.pt       # the CPU budget of the README's Mono row
    python ppo.py --steps 800000 --out ckpt/mono.pt --resume
    python evaluate.py --policy ckpt/mono.pt

Writes CKPT (actor only, train.py's format), CKPT.last.pt (resumable) and CKPT.csv: per update the
env steps, the mean return and success of the episodes that ended, and the losses.
"""
import argparse
import csv
import os
import time
from dataclasses import dataclass, asdict

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

import env
import model
from train import save_atomic   # atomic writes, as train.py checkpoints


@dataclass
class Config:
    steps: int = 800_000
    """env steps of training in all"""
    out: str = "ckpt/mono.pt"
    """checkpoint to write; CKPT.last.pt and CKPT.csv go beside it"""
    envs: int = 8
    """envs stepped in lock-step, one network call for all"""
    rollout: int = 256
    """steps per env between updates (a batch of envs x rollout steps)"""
    epochs: int = 4
    """passes over each batch"""
    minibatch: int = 512
    """samples per gradient step"""
    lr: float = 3e-4
    """Adam learning rate, annealed linearly to 0 (CleanRL)"""
    gamma: float = 0.99
    """discount"""
    gae_lambda: float = 0.95
    """GAE lambda"""
    clip: float = 0.2
    """PPO ratio clip"""
    value_coef: float = 0.5
    """weight of the value loss"""
    entropy_coef: float = 0.0
    """weight of the entropy bonus (CleanRL's continuous default: 0)"""
    max_grad_norm: float = 0.5
    """gradient clip"""
    d_model: int = 128
    """width of the actor's token (model.ModelConfig.d_model)"""
    max_steps: int = 1500
    """episode step limit (env.EnvConfig)"""
    seed: int = 0
    """seed of torch, the action sampling and the training episodes"""
    threads: int = 0
    """torch CPU threads (0: all cores)"""
    resume: bool = False
    """continue from CKPT.last.pt"""


class ActorCritic(nn.Module):
    """The no_skill network at context 1 (the actor's means and grip logits), a state-independent
    log-std, and a value head reading the same observation token x_t."""

    def __init__(self, margs):
        super().__init__()
        self.actor = model.SkillTransformer(margs)
        self.log_std = nn.Parameter(torch.full((9,), -0.5))   # arm 7 + base 2
        self.value = nn.Sequential(nn.Linear(margs.d_model, 128), nn.Tanh(), nn.Linear(128, 1))

    def forward(self, depth, state):
        """depth (N, 1, H, W) in [0, 1], state (N, S) -> (means (N, 9), grip logits (N, 3), value (N,))."""
        x = self.actor.embed_obs(depth[:, None], state[:, None])             # (N, 1, D)
        mask = torch.ones(x.shape[:2], dtype=torch.bool)
        out = self.actor.infer_action(x, None, mask)   # context 1, no memory: a reactive policy
        means = torch.cat([out["arm"][:, 0], out["base"][:, 0]], -1)
        return means, out["grip_logits"][:, 0], self.value(x[:, 0]).squeeze(-1)

    def dist(self, depth, state):
        means, grip_logits, value = self(depth, state)
        return torch.distributions.Normal(means, self.log_std.exp()), torch.distributions.Categorical(logits=grip_logits), value


def to_inputs(obs, size):
    """Observations of N envs -> (depth (N, 1, S, S) in [0, 1], quantised as the demos are; state (N, S))."""
    depth = np.stack([env.depth_to_uint8(o["depth"]) for o in obs]).astype(np.float32) / 255.0
    return torch.from_numpy(depth).view(len(obs), 1, size, size), torch.from_numpy(np.stack([env.state_vector(o, env.STATE_LAYOUT) for o in obs]))


def to_action(cont, grip):
    """Sampled (N, 9) means-space values and (N,) grip classes -> env actions (N, 10) in the box."""
    a = torch.cat([cont.clamp(-1, 1), torch.as_tensor(env.GRIP_VALUES)[grip][:, None]], -1)
    return a.numpy().astype(np.float32)


def checkpoint(net, opt, margs, cfg, env_config, steps, resumable):
    actor = {"model": {k: v.cpu() for k, v in net.actor.state_dict().items()}, "model_args": asdict(margs),
             "config": dict(asdict(cfg), variant="mono"), "env_config": env_config, "rtg_max": 0.0,
             "iter_num": steps, "n_demos": 0}
    return dict(actor, full=net.state_dict(), optimizer=opt.state_dict()) if resumable else actor


# --- training ---

def train(cfg, make_env=None):
    """PPO on the rearrangement env (or make_env(i) -> an env with the same interface, for tests)
    -> path of the checkpoint. Each env draws a new train episode at every reset."""
    if cfg.envs < 1 or cfg.rollout < 1 or cfg.minibatch < 1 or cfg.steps < cfg.envs * cfg.rollout:
        raise ValueError(f"need --envs, --rollout, --minibatch >= 1 and --steps >= envs x rollout "
                         f"({cfg.envs * cfg.rollout}); got {cfg.envs}, {cfg.rollout}, {cfg.minibatch}, {cfg.steps}")
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    torch.manual_seed(cfg.seed)
    env_config = asdict(env.EnvConfig(max_steps=cfg.max_steps))
    envs = [make_env(i) if make_env else env.RearrangeEnv(**env_config) for i in range(cfg.envs)]
    env_config = asdict(envs[0].config)   # what evaluate.py will run the actor in
    size = envs[0].config.depth_size
    episodes = env.make_episodes("train", 1000, seed=cfg.seed)   # the mix of Sec. 3, drawn in turn
    margs = model.ModelConfig(depth_size=size, state_layout=envs[0].state_layout, context=1, memory=0, d_vis=cfg.d_model // 2,
                              d_state=cfg.d_model - cfg.d_model // 2, d_model=cfg.d_model,
                              variant="no_skill", prev_action=False, skill_sample=0.0)
    net = ActorCritic(margs)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, eps=1e-5)
    stem = cfg.out[:-3] if cfg.out.endswith(".pt") else cfg.out
    last_path, csv_path = stem + ".last.pt", stem + ".csv"
    done_steps, resets = 0, 0
    if cfg.resume:
        ckpt = model.load_checkpoint(last_path)
        if ckpt["model_args"] != asdict(margs):
            raise ValueError(f"{last_path}: model settings differ from the command line's")
        net.load_state_dict(ckpt["full"])
        opt.load_state_dict(ckpt["optimizer"])
        done_steps = resets = int(ckpt["iter_num"])   # new reset seeds after a resume
        print(f"resuming {last_path} at {done_steps} steps")
    rng = np.random.default_rng([cfg.seed, done_steps])

    def reset(e):
        nonlocal resets
        resets += 1
        return e.reset(seed=int(rng.integers(2 ** 31)), options={"episode": episodes[resets % len(episodes)]})[0]

    obs = [reset(e) for e in envs]
    if not cfg.resume:   # state normalisation (no demos to take it from): one rollout of random actions
        states = []
        for _ in range(cfg.rollout):
            for i, e in enumerate(envs):
                a = np.r_[rng.uniform(-1, 1, 9), rng.choice(env.GRIP_VALUES)].astype(np.float32)
                obs[i], _, terminated, truncated, _ = e.step(a)
                states.append(env.state_vector(obs[i], env.STATE_LAYOUT))
                if terminated or truncated:
                    obs[i] = reset(e)
        net.actor.state_mean.copy_(torch.from_numpy(np.mean(states, 0)))
        net.actor.state_std.copy_(torch.from_numpy(np.maximum(np.std(states, 0), 0.05)))
        obs = [reset(e) for e in envs]
    new_csv = not (cfg.resume and os.path.exists(csv_path))
    os.makedirs(os.path.dirname(os.path.abspath(csv_path)), exist_ok=True)
    csv_file = open(csv_path, "w" if new_csv else "a", newline="")
    writer = csv.DictWriter(csv_file, ("steps", "episodes", "return", "success", "policy_loss", "value_loss", "std", "steps_s"))
    if new_csv:
        writer.writeheader()
    N, T = cfg.envs, cfg.rollout
    ep_return, t0, start = np.zeros(N), time.time(), done_steps
    while done_steps < cfg.steps:
        for g in opt.param_groups:
            g["lr"] = cfg.lr * (1.0 - done_steps / cfg.steps)
        buf = {k: [] for k in ("depth", "state", "cont", "grip", "logp", "value", "reward", "done")}
        finished = []
        with torch.no_grad():
            for _ in range(T):
                depth, state = to_inputs(obs, size)
                normal, cat, value = net.dist(depth, state)
                cont, grip = normal.sample(), cat.sample()
                logp = normal.log_prob(cont).sum(-1) + cat.log_prob(grip)
                actions = to_action(cont, grip)
                rewards, dones = np.zeros(N, np.float32), np.zeros(N, np.float32)
                for i, e in enumerate(envs):
                    obs[i], rewards[i], terminated, truncated, info = e.step(actions[i])
                    ep_return[i] += rewards[i]
                    if terminated or truncated:
                        finished.append((ep_return[i], bool(info.get("success", False))))
                        ep_return[i], dones[i], obs[i] = 0.0, 1.0, reset(e)
                for k, v in (("depth", depth), ("state", state), ("cont", cont), ("grip", grip), ("logp", logp),
                             ("value", value), ("reward", torch.from_numpy(rewards)), ("done", torch.from_numpy(dones))):
                    buf[k].append(v)
            next_value = net.dist(*to_inputs(obs, size))[2]
        b = {k: torch.stack(v) for k, v in buf.items()}                     # (T, N, ...)
        # GAE (Schulman et al. 2016); a truncated episode is treated as ended, as CleanRL does
        adv, last = torch.zeros(T, N), torch.zeros(N)
        for t in reversed(range(T)):
            nv = next_value if t == T - 1 else b["value"][t + 1]
            live = 1.0 - b["done"][t]
            delta = b["reward"][t] + cfg.gamma * nv * live - b["value"][t]
            last = delta + cfg.gamma * cfg.gae_lambda * live * last
            adv[t] = last
        ret = adv + b["value"]
        flat = {k: v.flatten(0, 1) for k, v in b.items()}
        flat["adv"], flat["ret"] = adv.flatten(), ret.flatten()
        for _ in range(cfg.epochs):
            for idx in torch.randperm(N * T).split(cfg.minibatch):
                normal, cat, value = net.dist(flat["depth"][idx], flat["state"][idx])
                logp = normal.log_prob(flat["cont"][idx]).sum(-1) + cat.log_prob(flat["grip"][idx])
                ratio = (logp - flat["logp"][idx]).exp()
                a = flat["adv"][idx]
                a = (a - a.mean()) / (a.std() + 1e-8)
                policy_loss = torch.max(-a * ratio, -a * ratio.clamp(1 - cfg.clip, 1 + cfg.clip)).mean()
                value_loss = F.mse_loss(value, flat["ret"][idx])
                entropy = normal.entropy().sum(-1).mean() + cat.entropy().mean()
                loss = policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * entropy
                opt.zero_grad(set_to_none=True)
                loss.backward()
                nn.utils.clip_grad_norm_(net.parameters(), cfg.max_grad_norm)
                opt.step()
        done_steps += N * T
        rate = (done_steps - start) / (time.time() - t0)
        row = {"steps": done_steps, "episodes": len(finished),
               "return": round(float(np.mean([r for r, _ in finished])), 3) if finished else "",
               "success": round(float(np.mean([s for _, s in finished])), 3) if finished else "",
               "policy_loss": round(policy_loss.item(), 4), "value_loss": round(value_loss.item(), 4),
               "std": round(float(net.log_std.detach().exp().mean()), 3), "steps_s": round(rate, 1)}
        writer.writerow(row)
        csv_file.flush()
        print(f"[{done_steps:9d}/{cfg.steps}] return {row['return']} success {row['success']} "
              f"({len(finished)} episodes) std {row['std']} | {rate:.0f} steps/s, "
              f"eta {(cfg.steps - done_steps) / rate / 60:.1f} min", flush=True)
        save_atomic(checkpoint(net, opt, margs, cfg, env_config, done_steps, True), last_path)
    save_atomic(checkpoint(net, opt, margs, cfg, env_config, done_steps, False), cfg.out)
    csv_file.close()
    print(f"done in {(time.time() - t0) / 60:.1f} min: {cfg.out}")
    return cfg.out


def parse_args(argv=None):
    """argparse generated from Config (env.add_config_args)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    return Config(**vars(env.add_config_args(p, Config).parse_args(argv)))


if __name__ == "__main__":
    train(parse_args())
