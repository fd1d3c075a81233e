"""Privileged scripted expert: solves the rearrangement task and labels every step with its skill.

The paper's demonstrations come from M3 (Oracle): RL skills sequenced by a planner that reads the
simulator (Appendix C.1). Ours are scripted controllers on the privileged state: navigation by a
wavefront planner on the layout's occupancy grid and path following; pick, place and opening by
damped-least-squares inverse kinematics on the end-effector site. With plan="fixed" it is the M3
baseline: navigate, pick, navigate, place, never opening anything. Neither re-plans (Appendix C.3).

    python expert.py --episodes 40 --split unseen               # success by difficulty
    python expert.py --episodes 40 --split unseen --plan fixed
"""
import argparse
import collections
import dataclasses
import time

import mujoco
import numpy as np

import env
from env import SKILL_IDS

# --- controller constants ---

NAV_CLEAR = 0.55            # m: preferred planning clearance of the base centre (robot radius 0.3 + 0.25)
NAV_INFLATE = 0.4           # m: the least clearance, where NAV_CLEAR leaves no path
NAV_DRIFT_DECAY = np.exp(-1 / 30)   # per step: the navigation noise drifts with a 1 s time constant
LOOKAHEAD = 0.35            # m: pure-pursuit lookahead along the path
NAV_TIMEOUT = 700           # steps per skill before it gives up
STANDOFF = {"surface": 0.45, "drawer": 0.72, "fridge": 0.45}   # base centre to the front face, m
REACH = {"surface": 0.6, "drawer": 0.58, "fridge": 0.6}       # base centre to the object or goal, m
DOOR_TARGET = 1.6           # rad the expert swings the fridge door to (range 1.75)
ARM_EASE = 3                # steps: the arm closes 1/ARM_EASE of its error per step near its target
REST_TOL = 0.2              # rad: a manipulation skill ends this near the folded pose (see _rest)
FUNNEL_HEIGHT = 0.15        # m: pick and place approach their point from this high above it (_approach)
FUNNEL_SLOPE = 2.0          # the aim is this many times the horizontal error above the point
PICK_TOL = 0.015            # m: the pick's approach ends this near the top of the object (if not yet held)
PLACE_TOL = 0.02            # m: ... and the place's this near the drop point
GRASP_ZONE = 0.1            # m: the suction is on for the last 10 cm of the pick's approach
RELEASE_ZONE = 0.12         # m: ... and off for the last 12 cm of the place's. At 4 cm learned places
                            # hovered the object 10-27 cm from the goal and never released (README,
                            # "The release round"); the oracle succeeds as often with 12 cm
DOWN = np.array([0.0, 0.0, -1.0])


@dataclasses.dataclass
class Args:
    episodes: int = 40
    """number of episodes to run"""
    split: str = "unseen"
    """episode set: train, seen or unseen"""
    plan: str = "oracle"
    """oracle (opens receptacles when needed) or fixed (navigate, pick, navigate, place)"""
    seed: int = 0
    """seed of the episode set and of the env resets"""
    noise: float = 0.0
    """std of Gaussian noise added to executed arm and base actions (DART)"""
    nav_noise: float = 0.0
    """std of a slowly drifting noise added to the executed turn rate while following a path (DART)"""
    jitter: float = 0.0
    """navigation to a pick or place ends up to this many rad off facing its point (DART)"""


class Expert:
    """Scripted skills on the privileged state; act() returns the clean action and its skill id."""

    def __init__(self, env_, plan="oracle", seed=0, noise=0.0, nav_noise=0.0, jitter=0.0):
        if plan not in ("oracle", "fixed"):
            raise ValueError(f"plan must be 'oracle' or 'fixed', got {plan!r}")
        self.env, self.plan = env_, plan
        self.noise, self.nav_noise, self.jitter = float(noise), float(nav_noise), float(jitter)
        self.rng = np.random.default_rng(seed)
        self.compute_time = 0.0

    # --- plan (decided once at reset, as M3 (Oracle); never re-planned) ---

    def reset(self):
        e = self.env
        self.p = e.privileged()
        self.m = e.model
        self.d_ik = mujoco.MjData(self.m)      # scratch data for inverse kinematics
        self.ids = e.ids
        self.fur = {f.name: f for f in self.p["layout"].furniture}
        ep = self.p["episode"]
        steps = []
        if self.plan == "oracle" and ep.goal_receptacle:
            steps += [("navigate", (self._open_pose(ep.goal_place), None)), ("open", ep.goal_receptacle - 1)]
        if self.plan == "oracle" and ep.obj_receptacle:
            steps += [("navigate", (self._open_pose(ep.object_places[ep.target]), None)), ("open", ep.obj_receptacle - 1)]
        # navigation to a pick or place ends facing its point at arm's reach (as M3's navigation
        # skill ends facing its target); obj_start is where the target started: in a drawer,
        # before the drawer was pulled out
        obj, place = ep.objects[ep.target], ep.object_places[ep.target]
        pulled = env.DRAWER_TRAVEL if place.startswith("drawer") else 0.0
        steps += [("navigate", (self._work_pose(place, obj), (obj, self._reach(place) + pulled))), ("pick", None),
                  ("navigate", (self._work_pose(ep.goal_place, ep.goal), (ep.goal, self._reach(ep.goal_place)))),
                  ("place", None)]
        self.steps = steps
        self.gen, self.skill = None, None
        self.drift, self.following = 0.0, False
        self.reach_step = -1                    # step of the current _approach, -1 outside one

    def act(self, obs, reward=0.0):
        """(action float32 (10,), skill id) for the current state; obs is unused: the expert is privileged."""
        t0 = time.perf_counter()
        self.p = self.env.privileged()
        action = None
        while action is None:
            if self.gen is None:
                if not self.steps:                  # plan finished: stay still
                    action = np.zeros(env.ACTION_DIM)
                    break
                kind, arg = self.steps.pop(0)
                self.gen = getattr(self, f"_{kind}")(arg)
                self.skill = self._skill_id(kind, arg)
            try:
                action = next(self.gen)
            except StopIteration:
                self.gen = None
        self.compute_time += time.perf_counter() - t0
        return np.asarray(action, np.float32), self.skill

    def noisy(self, action):
        """DART (Laskey et al. 2017): the env executes a perturbed action, the demo records the clean one.

        Per-step noise on arm and base, and while following a path a drift of the turn rate: noise
        that changes every 1/30 s averages out within centimetres, a drift carries the base tens of
        centimetres off its path, as a learned navigation strays, and the demo shows the way back."""
        if self.noise <= 0 and self.nav_noise <= 0:
            return action
        a = np.array(action, np.float32)
        if self.noise > 0:
            a[:9] += self.rng.normal(0.0, self.noise, 9)
        if self.nav_noise > 0:
            self.drift = NAV_DRIFT_DECAY * self.drift + np.sqrt(1 - NAV_DRIFT_DECAY ** 2) * self.rng.normal(0.0, self.nav_noise)
            if self.following:
                a[8] += self.drift
        a[:9] = np.clip(a[:9], -1, 1)
        return a

    def _skill_id(self, kind, arg):
        if kind == "open":
            return SKILL_IDS["open_fridge" if env.RECEPTACLES[arg] == "fridge" else "open_drawer"]
        return SKILL_IDS[kind]

    # --- geometry helpers ---

    def _furniture(self, place):
        return self.fur["cabinet" if place.startswith("drawer") else place]

    def _frame(self, f):
        """Furniture front normal (into the room), lateral axis, and front-face centre."""
        n = np.array([np.cos(f.yaw), np.sin(f.yaw)])
        lat = np.array([-n[1], n[0]])
        return n, lat, np.array(f.center) + n * f.size[0] / 2

    def _work_pose(self, place, point):
        """Base pose facing the furniture, in line with the point, STANDOFF from the front face."""
        f = self._furniture(place)
        n, lat, face = self._frame(f)
        kind = "drawer" if place.startswith("drawer") else f.kind
        offset = float(np.clip((np.asarray(point[:2]) - face) @ lat, -f.size[1] / 2 + 0.1, f.size[1] / 2 - 0.1))
        if kind == "fridge":                     # keep clear of the open door on the hinge side
            offset = 0.05
        xy = face + lat * offset + n * STANDOFF[kind]
        return (*xy, f.yaw + np.pi)

    def _open_pose(self, place):
        """Where the base stands to open the receptacle at `place` (env.interaction_poses)."""
        return self.p["poses"]["fridge_door" if place == "fridge" else "cabinet"]

    def _arm_action(self, q_des, base=(0.0, 0.0), grip=0.0):
        """Joint-delta action that moves the arm's target toward q_des: at the env's max rate while
        far, then proportionally (1/ARM_EASE of the error per step), so that the label is a smooth
        function of the observed joint_target: a max-rate label flips from +1 to -1 within one
        arm_delta (0.05 rad), which a learned arm smooths over and overshoots by tenths of a rad."""
        delta = (q_des - self.p["arm_target"]) / (ARM_EASE * self.env.config.arm_delta)
        return np.array([*np.clip(delta, -1, 1), *base, grip])

    def _ik(self, target, axis=None, base=None, q0=None, iters=80):
        """Damped least squares on ee_site position (+ cup axis, the ee x-axis); mujoco4.md Sec. 8."""
        m, d, ids = self.m, self.d_ik, self.ids
        d.qpos[:] = self.env.data.qpos
        if base is not None:
            d.qpos[ids["base_q"]] = base
        q = np.array(self.p["arm"] if q0 is None else q0, float)
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        site = ids["ee_site"]
        for _ in range(iters):
            d.qpos[ids["arm_q"]] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)              # the Jacobian needs comPos, not kinematics alone
            err = target - d.site_xpos[site]
            mujoco.mj_jacSite(m, d, jacp, jacr, site)
            if axis is not None:
                cur = d.site_xmat[site].reshape(3, 3)[:, 0]
                err = np.concatenate([err, 0.3 * np.cross(cur, axis)])
                J = np.vstack([jacp[:, ids["arm_v"]], 0.3 * jacr[:, ids["arm_v"]]])
            else:
                J = jacp[:, ids["arm_v"]]
            if np.linalg.norm(err[:3]) < 2e-3 and np.linalg.norm(err[3:]) < 0.02:
                break
            dq = J.T @ np.linalg.solve(J @ J.T + 1e-3 * np.eye(len(err)), err)
            q = np.clip(q + np.clip(dq, -0.3, 0.3), env.ARM_RANGE[:, 0] + 0.05, env.ARM_RANGE[:, 1] - 0.05)
        return q

    def _move_arm(self, q_des, tol=0.03, timeout=60, base=(0.0, 0.0), grip=0.0):
        """Yield actions until the arm joints are within tol of q_des (or timeout)."""
        for _ in range(timeout):
            if np.abs(self.p["arm"] - q_des).max() < tol:
                return
            yield self._arm_action(q_des, base, grip)

    def _path_arm(self, points, axis, tol=0.03, timeout=40):
        """Move the end effector through Cartesian waypoints (IK per waypoint, warm-started)."""
        q = self.p["arm"]
        for pt in points:
            q = self._ik(np.asarray(pt), axis, q0=q)
            yield from self._move_arm(q, tol, timeout)

    def _rest(self):
        """Fold the arm at the end of a manipulation skill, which ends once the arm is within
        REST_TOL of the folded pose; navigation's arm label (ARM_REST) finishes the fold. A held
        object stops the fold 0.12-0.14 rad short, so with a fine tolerance every pick ended on
        the timeout, a moment the policy cannot observe, and learned picks often never ended."""
        yield from self._move_arm(env.ARM_REST, tol=REST_TOL, timeout=80)

    # --- navigation: wavefront on the inflated occupancy grid, pure pursuit along the path ---

    def _blocked(self, inflate):
        """Occupancy for planning: furniture inflated by `inflate`, plus open drawers and doors."""
        p = self.p
        grid = env.occupancy_grid(p["layout"], inflate=inflate)
        res = p["grid_res"]
        X, Y = np.meshgrid((np.arange(grid.shape[0]) + 0.5) * res, (np.arange(grid.shape[1]) + 0.5) * res, indexing="ij")
        for k, rec in enumerate(env.RECEPTACLES):
            if p["open_fraction"][k] < 0.05:
                continue
            f = self.fur["fridge" if rec == "fridge" else "cabinet"]
            n, lat, face = self._frame(f)
            if rec == "fridge":                  # the door panel as a segment from the hinge
                th = p["open_fraction"][k] * env.DOOR_RANGE
                a = face - lat * f.size[1] / 2
                b = a + 2 * f.size[1] / 2 * (n * np.sin(th) + lat * np.cos(th))
            else:                                # the pulled drawer's front edge
                a = face + n * p["open_fraction"][k] * env.DRAWER_TRAVEL - lat * f.size[1] / 2
                b = a + lat * f.size[1]
            ab = b - a
            t = np.clip(((X - a[0]) * ab[0] + (Y - a[1]) * ab[1]) / (ab @ ab), 0, 1)
            grid |= np.hypot(X - a[0] - t * ab[0], Y - a[1] - t * ab[1]) < inflate
        return grid

    def _plan_path(self, start, goal):
        """A path with NAV_CLEAR of clearance, else with NAV_INFLATE, else straight for the goal. The
        wider berth leaves a learned navigation room for error around obstacles."""
        for inflate in (NAV_CLEAR, NAV_INFLATE):
            path = self._grid_path(start, goal, inflate)
            if path is not None:
                return path
        return [np.asarray(goal[:2])]

    def _grid_path(self, start, goal, inflate):
        """Shortest 8-connected grid path by a numpy wavefront from the goal, then shortcut; None if
        there is none."""
        res = self.p["grid_res"]
        blocked = self._blocked(inflate)
        cell = lambda xy: tuple(np.clip((np.asarray(xy) / res).astype(int), 0, np.array(blocked.shape) - 1))
        s, g = cell(start[:2]), cell(goal[:2])
        free, static_free = ~blocked, ~self.p["occupancy"]
        for i, j in (s, g):                      # start and goal may touch the inflation: free a disc
            disc = slice(max(i - 6, 0), i + 7), slice(max(j - 6, 0), j + 7)
            free[disc] |= static_free[disc]
        dist = np.full(free.shape, np.inf)
        dist[g] = 0
        front = np.zeros_like(free)
        front[g] = True
        k = 0
        while front.any() and np.isinf(dist[s]):
            k += 1
            nb = np.zeros_like(front)
            nb[1:] |= front[:-1]; nb[:-1] |= front[1:]; nb[:, 1:] |= front[:, :-1]; nb[:, :-1] |= front[:, 1:]
            nb[1:, 1:] |= front[:-1, :-1]; nb[:-1, :-1] |= front[1:, 1:]; nb[1:, :-1] |= front[:-1, 1:]; nb[:-1, 1:] |= front[1:, :-1]
            front = nb & free & np.isinf(dist)
            dist[front] = k
        if np.isinf(dist[s]):
            return None
        path, c = [s], s
        while c != g:                            # descend the wavefront
            i, j = c
            nbrs = [(i + a, j + b) for a in (-1, 0, 1) for b in (-1, 0, 1)
                    if (a or b) and 0 <= i + a < free.shape[0] and 0 <= j + b < free.shape[1]]
            c = min(nbrs, key=lambda x: dist[x])
            path.append(c)
        pts = [(np.array(c) + 0.5) * res for c in path]
        out = [pts[0]]                           # shortcut: keep a point only where sight breaks
        i = 0
        while i < len(pts) - 1:
            j = len(pts) - 1
            while j > i + 1 and not self._line_free(free, pts[i], pts[j], res):
                j -= 1
            out.append(pts[j])
            i = j
        out[-1] = np.asarray(goal[:2], float)
        return out

    @staticmethod
    def _line_free(free, a, b, res):
        n = int(np.linalg.norm(b - a) / (res / 2)) + 2
        ij = (np.linspace(a, b, n) / res).astype(int)
        return bool(free[ij[:, 0], ij[:, 1]].all())

    def _navigate(self, arg):
        pose, face = arg     # face: (point, reach) to end facing, else the turn to the pose's heading
        p = self.p
        path = self._plan_path(p["base"][:2], pose)
        cfg = self.env.config
        for _ in range(NAV_TIMEOUT):
            x, y, yaw = self.p["base"]
            pos = np.array([x, y])
            while len(path) > 1 and np.linalg.norm(path[0] - pos) < LOOKAHEAD:
                path.pop(0)
            goal_dist = np.linalg.norm(path[-1] - pos)
            if len(path) == 1 and goal_dist < 0.04:
                self.following = False
                yield from (self._turn_to(pose[2]) if face is None else self._settle(*face))
                return
            tgt = path[0]
            err = _wrap(np.arctan2(tgt[1] - y, tgt[0] - x) - yaw)
            w = np.clip(4.0 * err / cfg.ang_speed, -1, 1)
            v = 0.0 if abs(err) > 0.5 else np.clip(2.0 * goal_dist, 0.1, 1.0) * np.cos(err)
            self.following = True               # the drift of DART acts on the path following alone
            yield self._arm_action(env.ARM_REST, (v, w))
        self.following = False

    def _turn_to(self, yaw_des, timeout=120):
        """Turn in place to the heading yaw_des, the arm folded."""
        for _ in range(timeout):
            err = _wrap(yaw_des - self.p["base"][2])
            if abs(err) < 0.04:
                return
            yield self._arm_action(env.ARM_REST, (0.0, np.clip(3.0 * err / self.env.config.ang_speed, -0.6, 0.6)))

    def _drive_to(self, pose, timeout=80):
        """Short straight move along the current heading to the pose's projection (mobile pick/place)."""
        for _ in range(timeout):
            x, y, yaw = self.p["base"]
            h = np.array([np.cos(yaw), np.sin(yaw)])
            along = (np.asarray(pose[:2]) - [x, y]) @ h
            if abs(along) < 0.02:
                return
            yield self._arm_action(self.p["arm_target"], (np.clip(3 * along, -0.4, 0.4) / self.env.config.lin_speed, 0.0))

    def _reach(self, place):
        return REACH["drawer" if place.startswith("drawer") else self._furniture(place).kind]

    def _settle(self, point, reach):
        """End of a navigation to a pick or place: face the point, then drive along the heading
        until it is `reach` away. Both are functions of what the policy observes (obj_start_polar,
        goal_polar), so a learned navigation that stopped off the work pose finishes the same way. With jitter
        (DART) it stops up to `jitter` rad off facing and 0.4 `jitter` m off the distance: a learned
        navigation stops near, not at, its mark, and the arm's reach must have been shown from there."""
        yaw_off, reach_off = self.rng.uniform(-1, 1, 2) * [self.jitter, 0.4 * self.jitter] if self.jitter > 0 else (0, 0)
        for _ in range(120):
            x, y, yaw = self.p["base"]
            to = np.asarray(point[:2]) - [x, y]
            err = _wrap(np.arctan2(to[1], to[0]) + yaw_off - yaw)
            along = np.linalg.norm(to) - reach - reach_off
            if abs(err) < 0.04 and abs(along) < 0.02:
                return
            w = np.clip(3.0 * err / self.env.config.ang_speed, -0.6, 0.6)
            v = 0.0 if abs(err) > 0.3 else np.clip(3 * along, -0.4, 0.4) / self.env.config.lin_speed
            yield self._arm_action(env.ARM_REST, (v, w))

    # --- manipulation skills ---

    def _pick(self, _):
        k = self.p["target"]
        place = self.p["episode"].object_places[k]
        for attempt in range(3):                 # a missed grasp aims 1 cm lower
            yield from self._approach(place, lambda: self._pick_point(attempt), PICK_TOL, grip=1.0, zone=GRASP_ZONE)
            if self.p["held"] < 0:
                yield self._arm_action(self.p["arm_target"], grip=1.0)
            if self.p["held"] == k:
                break
        above = self.p["ee"] + [0, 0, 0.12]
        yield from self._path_arm([above], DOWN)
        yield from self._retract()
        yield from self._rest()

    def _place(self, _):
        ep = self.p["episode"]
        k = self.p["target"]
        if self.p["held"] == k:
            drop = self._drop_point()
            yield from self._approach(ep.goal_place, lambda: drop, PLACE_TOL, grip=-1.0, zone=RELEASE_ZONE)
        for _ in range(3):
            yield self._arm_action(self.p["arm_target"], grip=-1.0)
        yield from self._path_arm([self.p["ee"] + [0, 0, 0.1]], DOWN)
        yield from self._retract()
        yield from self._rest()

    def _pick_point(self, attempt=0):
        """Where the pick reaches: just above the target's top (1 cm lower per missed attempt)."""
        return self.p["objects"][self.p["target"]] + [0, 0, env.OBJ_HALF + 0.005 - 0.01 * attempt]

    def _drop_point(self):
        """Where the place reaches: the cup 4 cm above the goal, the held object hanging below it."""
        offset = self.p["ee"] - self.p["objects"][self.p["target"]]
        return np.asarray(self.p["goal"]) + offset + [0, 0, 0.04]

    def _approach(self, place, point, tol, grip, zone, timeout=150):
        """Bring the cup, pointing down, to point() (re-read every step) from above, closed loop:
        every step aims FUNNEL_SLOPE x the horizontal error (at most FUNNEL_HEIGHT) above the point
        and moves the arm toward the IK solution of that aim found from the measured joints (not
        from the last solution: the arm is redundant, and a policy cannot see which solution the
        expert tracked). The label is then a function of the current observation (joints,
        set-point, target minus cup), not of a hidden waypoint index: with fixed waypoints (top
        + 15 cm, + 5 cm, top), the learned picks that missed stopped 7-24 cm from the object and
        commanded the grasp there (README, "The closed-loop reach round").

        Within `zone` of the point the grip command is `grip` (+1 grasp, -1 release), and the
        approach ends once it has taken effect: the suction takes an object up to 3 cm away
        (env.GRASP_DIST), so a learned reach that stops a few cm short still grasps, and the grip
        label is a function of the observed distance, not one step at the end of the reach (with
        one grasp step, learned picks came within 2-7 cm of the object and never grasped: README)."""
        for step in range(timeout):
            pt = np.asarray(point(), float)
            if np.linalg.norm(pt - self.p["ee"]) < tol or (self.p["held"] >= 0) == (grip > 0):
                break                           # there, or the grip took effect
            self.reach_step = step              # DAgger (collect.py --policy) reads where a reach is
            yield self._reach_step(place, pt, grip, zone)
        self.reach_step = -1

    def _reach_step(self, place, pt, grip, zone):
        """One step of _approach's closed-loop reach toward pt -> action."""
        ee = self.p["ee"]
        err = pt - ee
        e_xy = np.linalg.norm(err[:2])
        aim = pt + [0, 0, min(FUNNEL_HEIGHT, FUNNEL_SLOPE * e_xy)]
        # reaching out from rest would sweep the forearm (and a held object) through the edge
        # of a counter higher than the folded cup: first raise the cup in place
        if self._furniture(place).kind == "surface" and e_xy > 0.15 and ee[2] < pt[2] + FUNNEL_HEIGHT - 0.03:
            aim = np.array([*ee[:2], pt[2] + FUNNEL_HEIGHT])
        grip = grip if np.linalg.norm(err) < zone else 0.0
        return self._arm_action(self._ik(aim, DOWN, q0=self.p["arm"], iters=30), grip=grip)

    def reach_action(self, kind):
        """The action of the pick ("pick") or place ("place") reach in the current state, outside
        the plan, or None where that reach does not apply (a pick with something held, a place
        without the target). evaluate.py --assist reach runs it in place of a policy's arm and
        grip, to measure what the rest of the policy achieves (README, the DAgger round)."""
        self.p = p = self.env.privileged()
        ep = p["episode"]
        if kind == "pick" and p["held"] < 0:
            return self._reach_step(ep.object_places[p["target"]], self._pick_point(), 1.0, GRASP_ZONE)
        if kind == "place" and p["held"] == p["target"]:
            return self._reach_step(ep.goal_place, self._drop_point(), -1.0, RELEASE_ZONE)
        return None

    def _retract(self):
        """Pull the end effector out of a drawer or the fridge before folding the arm."""
        ee = self.p["ee"]
        for name in ("fridge", "cabinet"):
            f = self.fur[name]
            n, _, face = self._frame(f)
            if (ee[:2] - face) @ n < 0.1:       # still in front of / inside this piece's face?
                rel = ee[:2] - np.array(f.center)
                if np.abs(rel @ np.array([-n[1], n[0]])) < f.size[1] / 2 + 0.1:
                    out = np.array([*(face + n * 0.2), ee[2]])
                    yield from self._path_arm([out], None)

    def _open(self, k):
        rec = env.RECEPTACLES[k]
        f = self.fur["fridge" if rec == "fridge" else "cabinet"]
        n, lat, face = self._frame(f)
        into = np.array([-n[0], -n[1], 0.0])
        handle = self.p["handles"][k]
        out = np.array([*n, 0.0])
        yield from self._path_arm([handle + out * 0.3, handle + out * 0.15, handle + out * 0.05], into)   # clear of the front first
        # the last 6 cm with the suction on, aiming 1 cm past the handle's axis: the cup takes the
        # handle on the way in, so a learned reach that falls a few cm short still takes it
        q = self._ik(handle - out * 0.01, into)
        for _ in range(30):
            if self.p["handle"] == k:
                break
            yield self._arm_action(q, grip=1.0)
        if self.p["handle"] == k:
            if rec == "fridge":
                yield from self._swing_door(k, f)
            else:                                # Sec. 3: pull the drawer by backing the base away
                for _ in range(60):
                    if self.p["open_fraction"][k] > 0.97:
                        break
                    yield self._arm_action(self.p["arm_target"], (-0.3 / self.env.config.lin_speed, 0.0))
        for _ in range(2):
            yield self._arm_action(self.p["arm_target"], grip=-1.0)
        ee = self.p["ee"]
        if rec == "fridge":                      # off the handle, then out past the door's free edge
            th = self.p["open_fraction"][k] * env.DOOR_RANGE
            away = np.array([*(n * np.cos(th) - lat * np.sin(th)), 0.0])
            panel = np.array([*(n * np.sin(th) + lat * np.cos(th)), 0.0])
            past = ee + away * 0.05 + panel * 0.2
            yield from self._path_arm([ee + away * 0.05, past, past - away * 0.25], None)   # round the edge
            x, y, yaw = self.p["base"]
            yield from self._drive_to((*(np.array([x, y]) + n * 0.25), yaw))          # room to fold the arm
        else:                                    # straight back from the drawer handle
            yield from self._path_arm([ee + np.array([*n, 0.0]) * 0.12], None)
        yield from self._rest()

    def _swing_door(self, k, f):
        """Follow the grasp point's arc around the hinge with the arm, the cup square to the door.

        The arc starts where the cup took the handle (the suction's anchor), which with the suction
        on during the approach can be a few cm off the handle's axis."""
        n, lat, face = self._frame(f)
        hinge = face + n * 0.015 - lat * f.size[1] / 2
        h0 = self.p["ee"]
        th0 = self.p["open_fraction"][k] * env.DOOR_RANGE
        a, b = (h0[:2] - hinge) @ n, (h0[:2] - hinge) @ lat
        r_n, r_l = np.cos(th0) * a - np.sin(th0) * b, np.sin(th0) * a + np.cos(th0) * b   # at angle 0
        q = self.p["arm"]
        for th in np.arange(th0 + 0.1, DOOR_TARGET + 1e-6, 0.1):
            c, s = np.cos(th), np.sin(th)           # the door turns from lat toward n
            hxy = hinge + n * (r_n * c + r_l * s) + lat * (-r_n * s + r_l * c)
            into = -np.array([*(n * c - lat * s), 0.0])
            q = self._ik(np.array([*hxy, h0[2]]), into, q0=q)
            yield from self._move_arm(q, tol=0.04, timeout=20)
            if self.p["handle"] != k:
                return


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


# --- command line: success by difficulty, failure reasons, steps per skill ---

def run(args):
    e = env.RearrangeEnv()
    x = Expert(e, plan=args.plan, seed=args.seed, noise=args.noise, nav_noise=args.nav_noise, jitter=args.jitter)
    eps = env.make_episodes(args.split, args.episodes, seed=args.seed)
    by_diff = collections.defaultdict(list)
    failures = collections.Counter()
    skill_steps = collections.Counter()
    agree, total_steps, lengths = 0, 0, []
    t0 = time.perf_counter()
    e.timing = dict.fromkeys(e.timing, 0.0)
    for i, ep in enumerate(eps):
        obs, info = e.reset(seed=args.seed + i, options={"episode": ep})
        x.reset()
        done = False
        while not done:
            gt = info["skill_gt"]
            a, skill = x.act(obs)
            agree += int(skill == gt)
            skill_steps[env.SKILLS[skill]] += 1
            obs, r, term, trunc, info = e.step(x.noisy(a))
            done = term or trunc
            total_steps += 1
        by_diff[ep.difficulty].append(info["success"])
        lengths.append(info["steps"])
        failures[info["failure"] or ("success" if info["success"] else "ended")] += 1
        el = time.perf_counter() - t0
        print(f"[{i + 1:4d}/{len(eps)}] {ep.kind:13s} layout {ep.layout:4d} {'ok  ' if info['success'] else 'FAIL'} "
              f"{info['steps']:4d} steps {info['failure'] or ''}  ({(i + 1) / el * 60:.1f} ep/min, eta {(len(eps) - i - 1) * el / (i + 1) / 60:.1f} min)",
              flush=True)
    allv = [s for v in by_diff.values() for s in v]
    print(f"\nplan={args.plan} split={args.split} episodes={len(eps)}")
    print(f"success: all {100 * np.mean(allv):.1f} %  " + "  ".join(
        f"{d} {100 * np.mean(by_diff[d]):.1f} % (n={len(by_diff[d])})" for d in env.DIFFICULTIES if by_diff[d]))
    print("outcomes:", dict(failures))
    print(f"median episode length {np.median(lengths):.0f} steps; label agreement with skill_gt {100 * agree / total_steps:.1f} %")
    print("mean steps per skill per episode:", {k: round(v / len(eps), 1) for k, v in skill_steps.items()})
    env_time = sum(e.timing.values())
    print(f"expert compute {1e3 * x.compute_time / total_steps:.3f} ms/step = {100 * x.compute_time / env_time:.1f} % of env step time")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    docs = env.field_docs(Args)
    for f in dataclasses.fields(Args):
        p.add_argument(f"--{f.name.replace('_', '-')}", type=type(f.default), default=f.default, help=docs.get(f.name))
    args = Args(**vars(p.parse_args()))
    if args.split not in env.SPLITS or args.plan not in ("oracle", "fixed"):
        p.error(f"--split must be one of {tuple(env.SPLITS)} and --plan oracle or fixed, got {args.split!r}, {args.plan!r}")
    run(args)


if __name__ == "__main__":
    main()
