"""Privileged scripted expert: solves the rearrangement task and labels every step with its skill.

The paper's demonstrations come from M3 (Oracle): closed-loop RL skills on the current observation, sequenced
by a planner that reads the simulator and re-plans (Appendix C.1). Ours are scripted state-feedback controllers
on the privileged state, and the expert is a function of the current state alone: every step it (1) chooses the
skill from the world as it is now (is the target held, is its or the goal's receptacle closed, where are the
robot and the arm) and (2) computes that skill's action by feedback. No timers, counters, waypoint indices or
targets kept from earlier steps: a simulator state restored into a fresh env and expert gives the same action
and skill. So it recovers from whatever the state shows (a drawer pushed shut is opened again, a dropped object
picked again, a missed place retried) and can label any state a learner reaches (DAgger: `collect.py --policy CKPT`).

Navigation follows a distance field on the layout's occupancy grid (cached per layout, goal and open receptacles);
pick, place and opening move the arm toward a damped-least-squares IK solution found from the measured joints
every step. plan="fixed" is the M3 baseline: navigate, pick, navigate, place, never opening anything;
plan="tpsrl" is that plan with the base still while the arm works (TP-SRL, Szot et al. 2021, whose manipulation
skills do not move the base; ours nudge it to keep facing the point).

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

NAV_CLEAR = 0.55            # m: preferred clearance of the base centre (robot radius 0.3 + 0.25)
NAV_INFLATE = 0.4           # m: the least clearance; cells between the two cost NAV_NEAR_COST each
NAV_NEAR_COST = 4.0         # so a path takes the wide berth unless it is much longer
CONTACT_FORCE = 100.0       # N: navigation backs off from a contact this strong
DOOR_MARGIN = 0.15          # m: extra clearance from an open door or drawer
NAV_DRIFT_DECAY = np.exp(-1 / 30)   # per step: the navigation noise drifts with a 1 s time constant
FIELD_POOL = 2              # the distance field's cells are 2 x 2 occupancy cells (0.1 m): 8 times faster
LOOKAHEAD = 4               # field cells (0.4 m) along the descent of the distance field to aim at
ARRIVE = 0.05               # m: navigation has reached its pose's position; then it turns or settles
STANDOFF = {"surface": 0.45, "drawer": 0.72, "fridge": 0.45}   # base centre to the front face, m
REACH = {"surface": 0.6, "drawer": 0.58, "fridge": 0.6}       # base centre to the object or goal, m
WORK_YAW, WORK_DIST = 0.2, 0.1      # rad, m: a pick or place starts this near facing its point at reach
OPEN_XY, OPEN_YAW = 0.08, 0.08      # m, rad: an opening starts this near its pose
NEED_OPEN = 0.75            # a receptacle opened less than this fraction must be opened (to DRAWER_DONE, DOOR_DONE)
CARRY_OPEN = 0.4            # ... with the target in the cup, below this (a door nudged a bit shut is placed through)
DRAWER_DONE = 0.97          # fraction at which the drawer pull lets go
DOOR_DONE = 1.5             # rad at which the door swing lets go (range 1.75; the arm's reach ends ~1.58)
DOOR_TARGET = 1.6           # rad the swing's aim never passes
DOOR_STEP = 0.3             # rad: each step the swing aims this far ahead of the door's angle
ARM_EASE = 3                # steps: the arm closes 1/ARM_EASE of its error per step near its target
REST_TOL = 0.2              # rad: the arm is folded this near ARM_REST (a held object stops it 0.12-0.14 short)
FUNNEL_HEIGHT = 0.15        # m: pick and place approach their point from this high above it
FUNNEL_HEIGHT_FRIDGE = 0.08 # ... in the fridge, whose upper shelf leaves the wrist little room
FUNNEL_SLOPE = 2.0          # the aim is this many times the horizontal error above the point
GRASP_ZONE = 0.1            # m: the suction is on for the last 10 cm of the pick's approach
RELEASE_ZONE = 0.12         # m: ... and off for the last 12 cm of the place's (at 4 cm learned places
                            # hovered near the goal and never released: EXPERIMENTS.md, E10)
PLACE_TOL = 0.03            # m: the place releases at the latest this near its drop point ...
DROP_XY = 0.08              # ... or with the object this near the goal horizontally and low over it
LIFT = 0.03                 # m: a held object is lifted (and drawn in) until this much air is under it
DONE_DIST = 0.12            # m: the target this near the goal and not held: the place is done
# base feedback gains (actions are divided by the env's lin_speed and ang_speed)
TURN_GAIN = 3.0             # rad/s of turn per rad of heading error, settling on or holding a pose
ALONG_GAIN = 3.0            # m/s per m of distance error along the heading
SETTLE_TURN, SETTLE_SPEED = 0.6, 0.4   # action limits while settling at reach or holding a work pose
SETTLE_FACING = 0.3         # rad: the base closes the distance only when it faces the point this well
HOLD_TURN, HOLD_SPEED = 0.5, 0.3       # action limits while the arm works a handle from a pose
NAV_TURN_GAIN = 4.0         # navigation: turn per rad of error toward the look-ahead point
NAV_FACING = 0.5            # rad: it drives forward only when it faces the look-ahead point this well
NAV_SPEED_GAIN, NAV_MIN_SPEED = 2.0, 0.1   # m/s per m to the goal, between NAV_MIN_SPEED and full speed
BACK_OFF = 0.3              # m/s: away from a contact, pulling a drawer, or off the fridge door
FOLD_ROOM = 1.15            # m: the base backs off to this far from the fridge's face before the fold
DOWN = np.array([0.0, 0.0, -1.0])
PLANS = ("oracle", "fixed", "tpsrl")


@dataclasses.dataclass
class Args:
    episodes: int = 40
    """number of episodes to run"""
    split: str = "unseen"
    """episode set: train, seen or unseen"""
    plan: str = "oracle"
    """oracle (opens receptacles when needed), fixed (navigate, pick, navigate, place) or tpsrl
    (fixed, the base still while the arm works)"""
    seed: int = 0
    """seed of the episode set and of the env resets"""
    noise: float = 0.0
    """std of Gaussian noise added to the executed arm (and, while navigating, base) actions (DART)"""
    nav_noise: float = 0.0
    """std of a slowly drifting noise added to the executed turn rate while navigating (DART)"""
    perturb: bool = False
    """Sec. 5.4: the target's receptacle snaps shut once after it has been open for perturb_after steps"""
    perturb_after: int = 50
    """steps the target's receptacle must have been open before the perturbation fires"""


class Expert:
    """State-feedback skills on the privileged state; act() returns the clean action and its skill id."""

    def __init__(self, env_, plan="oracle", seed=0, noise=0.0, nav_noise=0.0):
        if plan not in PLANS:
            raise ValueError(f"plan must be one of {PLANS}, got {plan!r}")
        self.env, self.plan = env_, plan
        self.noise, self.nav_noise = float(noise), float(nav_noise)
        self.rng = np.random.default_rng(seed)   # the DART noise's, never the label's
        self.fields = {}                         # (layout, goal cell, open receptacles) -> distance field
        self.drift, self.skill, self.compute_time = 0.0, SKILL_IDS["navigate"], 0.0

    def reset(self):
        """Start of an episode: only the noise process restarts; the labels have no memory."""
        self.drift = 0.0

    def act(self, obs=None, reward=0.0):
        """(action float32 (10,), skill id) for the current state; obs is unused: the expert is privileged."""
        t0 = time.perf_counter()
        self.observe()
        skill, action = self._decide()
        if self.plan == "tpsrl" and skill != "navigate":
            action = np.r_[action[:7], 0.0, 0.0, action[9]]   # TP-SRL: the base stands while the arm works
        self.skill = SKILL_IDS[skill]
        self.compute_time += time.perf_counter() - t0
        return np.asarray(action, np.float32), self.skill

    def observe(self):
        """Read the simulator's privileged state: what every decision and geometry test below uses."""
        self.p, self.m, self.ids = self.env.privileged(), self.env.model, self.env.ids
        self.fur = {f.name: f for f in self.p["layout"].furniture}

    def noisy(self, action):
        """DART (Laskey et al. 2017): the env executes a perturbed action, the demo records the clean one.

        Per-step noise on the arm, and while navigating on the base plus a drift of the turn rate: noise that
        changes every 1/30 s averages out within centimetres, a drift carries the base tens of centimetres off its
        path as a learned navigation strays, and the demo shows the way back. Manipulation's base is not noised."""
        if self.noise <= 0 and self.nav_noise <= 0:
            return action
        a = np.array(action, np.float32)
        navigating = self.skill == SKILL_IDS["navigate"]
        if self.noise > 0:
            a[:9 if navigating else 7] += self.rng.normal(0.0, self.noise, 9 if navigating else 7)
        if self.nav_noise > 0:
            self.drift = NAV_DRIFT_DECAY * self.drift + np.sqrt(1 - NAV_DRIFT_DECAY ** 2) * self.rng.normal(0.0, self.nav_noise)
            if navigating:
                a[8] += self.drift
        a[:9] = np.clip(a[:9], -1, 1)
        return a

    # --- the skill, chosen from the world as it is now (the planner of M3 (Oracle), re-run every step) ---

    def _decide(self):
        """-> (skill name, action). Each branch reads only the current privileged state."""
        p, ep, k = self.p, self.p["episode"], self.p["target"]
        shut = p["open_fraction"] < NEED_OPEN                   # receptacles that must be opened
        if p["handle"] >= 0:                                     # holding a handle: open it, then let go
            return self.open_skill(p["handle"]), self._operate_handle(p["handle"])
        if p["held"] >= 0 and p["held"] != k:                    # a distractor in the cup: put it down
            return "place", self._hold(grip=-1.0)
        goal_closed = self.plan == "oracle" and ep.goal_receptacle and shut[ep.goal_receptacle - 1]
        if p["held"] == k:
            # the goal's receptacle shut: it cannot be opened with the object in the cup, so put it
            # down, open, pick again (collect.py's events never shut it while the target is carried)
            if goal_closed and p["open_fraction"][ep.goal_receptacle - 1] < CARRY_OPEN:
                return "place", self._hold(grip=-1.0)
            point, place, skill, fold_skill = np.asarray(p["goal"]), ep.goal_place, "place", "pick"
        else:
            obj, r = p["objects"][k], p["obj_receptacle"] - 1
            v = self.ids["obj_v"][k]
            if np.linalg.norm(self.env.data.qvel[v:v + 3]) > 0.05:    # released or dropped: let it land
                return ("place" if np.linalg.norm(obj - p["goal"]) < 0.3 else "pick"), self._hold()
            if np.linalg.norm(obj - p["goal"]) < DONE_DIST:           # placed: clear the arm
                return "place", self._stow()
            if goal_closed or (self.plan == "oracle" and r >= 0 and shut[r]):   # open a receptacle
                sub = ep.goal_receptacle - 1 if goal_closed else r
                pose = p["poses"]["fridge_door" if env.RECEPTACLES[sub] == "fridge" else "cabinet"]
                if self.at_pose(pose):
                    return self.open_skill(sub), self._grab_handle(sub)
                if not self.folded():
                    return self._stow_skill(), self._stow()
                return "navigate", self._navigate(pose)
            point, place, skill, fold_skill = obj, self.support(obj), "pick", self._stow_skill()
        if self.at_work(point, place):
            return skill, self._place_step(point, place) if skill == "place" else self._pick_step(point, place)
        if not self.folded():
            return fold_skill, self._stow()
        return "navigate", self._navigate(self._work_pose(place, point), face=(point, self._reach(place)))

    # Public: collect.py's events and evaluate.py's BC-Modular planner ask these of the state too.

    def open_skill(self, r):
        """The skill that opens RECEPTACLES[r]: open_fridge or open_drawer."""
        return "open_fridge" if env.RECEPTACLES[r] == "fridge" else "open_drawer"

    def _stow_skill(self):
        """The skill that folds an empty arm: the opening whose handle it is near, else the pick."""
        p = self.p
        near = [r for r in range(len(env.RECEPTACLES))
                if p["open_fraction"][r] > 0.3 and np.linalg.norm(p["ee"] - p["handles"][r]) < 0.6]
        return self.open_skill(near[0]) if near else "pick"

    def folded(self):
        """The arm's set-point (observed as joint_target) is folded (so an arm a contact holds off it counts)."""
        return np.abs(self.p["arm_target"] - env.ARM_REST).max() < REST_TOL

    # --- geometry ---

    def _frame(self, f):
        """Furniture front normal (into the room), lateral axis, and front-face centre."""
        n = np.array([np.cos(f.yaw), np.sin(f.yaw)])
        lat = np.array([-n[1], n[0]])
        return n, lat, np.array(f.center) + n * f.size[0] / 2

    def support(self, pt):
        """Name of the place under a point: a surface, a drawer (pulled out or not) or the fridge."""
        for f in self.p["layout"].furniture:
            if f.kind not in ("surface", "cabinet", "fridge"):
                continue
            n, lat, face = self._frame(f)
            front = (pt[:2] - face) @ n                           # > 0: in front of the face
            inside = -f.size[0] - 0.05 < front < (env.DRAWER_TRAVEL + 0.05 if f.kind == "cabinet" else 0.05)
            if inside and abs((pt[:2] - face) @ lat) < f.size[1] / 2 + 0.05:
                if f.kind == "cabinet":
                    return "drawer_1" if pt[2] < (env.DRAWER_Z[0] + env.DRAWER_Z[1]) / 2 + 0.1 else "drawer_0"
                return f.name
        return "floor"

    def _kind(self, place):
        return "drawer" if place.startswith("drawer") else "surface" if place == "floor" else self.fur[place].kind

    def _reach(self, place):
        return REACH[self._kind(place)]

    def _work_pose(self, place, point):
        """Base pose facing the point at arm's reach, in line with it from STANDOFF before the face."""
        kind = self._kind(place)
        if place == "floor":                                     # no furniture: come at it from here
            w = np.asarray(self.p["base"][:2])
        else:
            f = self.fur["cabinet" if kind == "drawer" else place]
            n, lat, face = self._frame(f)
            offset = float(np.clip((np.asarray(point[:2]) - face) @ lat, -f.size[1] / 2 + 0.1, f.size[1] / 2 - 0.1))
            if kind == "fridge":                     # keep clear of the open door on the hinge side
                offset = 0.12
            w = face + lat * offset + n * STANDOFF[kind]
        u = (point[:2] - w) / max(np.linalg.norm(point[:2] - w), 1e-6)
        return (*(point[:2] - u * REACH[kind]), np.arctan2(u[1], u[0]))   # on the line from w, at reach

    def at_work(self, point, place):
        """Facing the point at arm's reach: where a pick or place acts (its base label keeps it there)."""
        x, y, yaw = self.p["base"]
        to = np.asarray(point[:2]) - [x, y]
        return (abs(_wrap(np.arctan2(to[1], to[0]) - yaw)) < WORK_YAW
                and abs(np.linalg.norm(to) - self._reach(place)) < WORK_DIST)

    def at_pose(self, pose):
        """Near an opening pose (x, y, yaw), within OPEN_XY and OPEN_YAW."""
        x, y, yaw = self.p["base"]
        return np.hypot(pose[0] - x, pose[1] - y) < OPEN_XY and abs(_wrap(pose[2] - yaw)) < OPEN_YAW

    # --- arm ---

    def _arm_action(self, q_des, base=(0.0, 0.0), grip=0.0):
        """Joint-delta action moving the arm's set-point toward q_des: at the env's max rate while far, then
        1/ARM_EASE of the error per step, so the label is a smooth function of the observed joint_target (a
        max-rate label flips sign within one arm_delta, which a learned arm smooths over and overshoots)."""
        delta = (q_des - self.p["arm_target"]) / (ARM_EASE * self.env.config.arm_delta)
        return np.array([*np.clip(delta, -1, 1), *base, grip])

    def _hold(self, base=(0.0, 0.0), grip=0.0):
        return self._arm_action(self.p["arm_target"], base, grip)

    def _ik(self, target, axis=None, iters=30):
        """Damped least squares on ee_site position (+ cup axis, the ee x-axis), from the measured
        joints (the arm is redundant: a solution tracked from an earlier step would be hidden state)."""
        m, ids, site = self.m, self.ids, self.ids["ee_site"]
        if getattr(self, "d_ik_model", None) is not m:
            self.d_ik, self.d_ik_model = mujoco.MjData(m), m     # scratch data, rebuilt per layout model
        di = self.d_ik
        di.qpos[:] = self.env.data.qpos
        q = np.array(self.p["arm"], float)
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        lo, hi = env.ARM_RANGE[:, 0] + 0.05, env.ARM_RANGE[:, 1] - 0.05
        damp = 1e-3 * np.eye(3 if axis is None else 6)
        for _ in range(iters):
            di.qpos[ids["arm_q"]] = q
            mujoco.mj_kinematics(m, di)
            mujoco.mj_comPos(m, di)              # the Jacobian needs comPos, not kinematics alone
            err = target - di.site_xpos[site]
            mujoco.mj_jacSite(m, di, jacp, jacr, site)
            J = jacp[:, ids["arm_v"]]
            if axis is not None:                 # + 0.3 x (cup axis x target axis)
                err = np.concatenate([err, 0.3 * np.cross(di.site_xmat[site].reshape(3, 3)[:, 0], axis)])
                J = np.vstack([J, 0.3 * jacr[:, ids["arm_v"]]])
            if err[:3] @ err[:3] < 4e-6 and err[3:] @ err[3:] < 4e-4:
                break
            dq = J.T @ np.linalg.solve(J @ J.T + damp, err)
            q = np.minimum(np.maximum(q + np.minimum(np.maximum(dq, -0.3), 0.3), lo), hi)
        return q

    def _clearance(self, body, half=env.OBJ_HALF):
        """Air under a body (m): a ray straight down from `half` below its centre, missing the robot and body."""
        start = self.env.data.xpos[body] - [0, 0, half + 0.002]
        gid = np.zeros(1, np.int32)      # env's depth camera's geom groups: the robot left out
        dist = mujoco.mj_ray(self.m, self.env.data, start, DOWN, self.env._geomgroup, 1, int(body), gid)
        return np.inf if dist < 0 else dist

    def _stow(self):
        """Fold the arm by the way out the cup's position calls for: lift a held object off its support, leave
        a drawer handle straight back, go round the open fridge door's free edge, pull the cup out of furniture,
        then (or where the way out is out of reach: IK stays where the arm is) fold in joint space."""
        p, ee, aim = self.p, self.p["ee"], None
        # up and toward the base (straight up is out of reach for an arm stretched over a counter),
        # the cup's orientation free: the weld carries the object whatever it is
        if p["held"] == p["target"] and self._clearance(self.ids["obj_body"][p["target"]]) < LIFT:
            inward = np.array([*(np.asarray(p["base"][:2]) - ee[:2]), 0.0])
            aim = ee + [0, 0, 0.05] + inward * (0.15 / max(np.linalg.norm(inward), 1e-6))
        elif p["held"] < 0:
            near = [r for r in range(2) if np.linalg.norm(ee - p["handles"][r]) < 0.08]
            below = self._clearance(self.ids["ee_body"], 0.0)
            if below < 0.1 and below < ee[2] - 0.05:             # low over a surface or an object:
                aim = ee + [0, 0, 0.12]                          # up first, the fold would sweep it
            elif near:                                           # off a drawer handle, straight back
                aim = p["handles"][near[0]] + [*self._frame(self.fur["cabinet"])[0] * 0.14, 0.0]
            else:
                aim = self._door_way_out()
                if isinstance(aim, tuple):                       # the base backs off instead
                    return self._hold(base=aim)
        if aim is None:
            for name in ("fridge", "cabinet"):                   # out of the furniture's front first
                f = self.fur[name]
                n, lat, face = self._frame(f)
                if (ee[:2] - face) @ n < 0.1 and abs((ee[:2] - face) @ lat) < f.size[1] / 2 + 0.1:
                    aim = np.array([*(face + n * 0.2), ee[2]])
        if aim is not None:
            q = self._ik(aim)
            if np.abs(q - p["arm"]).max() > 0.03 or np.linalg.norm(aim - ee) < 0.03:
                return self._arm_action(q)
        return self._arm_action(env.ARM_REST)

    def _door_way_out(self):
        """The way back from the fridge door's handle, by where the cup is in the door's frame: s along the
        panel from the hinge, h off its outer face (which has the handle and which the open door turns away
        from the robot): away from the panel, past its free edge, round to the robot's side, then back the base
        off so the arm has room to fold. -> an aim for the cup, a base action (v, w), or None (not near)."""
        p = self.p
        frac = p["open_fraction"][env.RECEPTACLES.index("fridge")]
        if frac < 0.3:
            return None
        f = self.fur["fridge"]
        n, lat, face = self._frame(f)
        th, width, ee = frac * env.DOOR_RANGE, f.size[1], p["ee"]
        hinge = face + n * env.DOOR_HALF - lat * width / 2
        along = n * np.sin(th) + lat * np.cos(th)                # the panel, hinge to free edge
        out = n * np.cos(th) - lat * np.sin(th)                  # the panel's outer normal
        s, h = (ee[:2] - hinge) @ along, (ee[:2] - hinge) @ out
        if not (-0.1 < s < width + 0.4 and -0.35 < h < 0.3):
            return None
        at = lambda s_, h_: np.array([*(hinge + along * s_ + out * h_), ee[2]])
        if h >= 0 and s < width + 0.12:
            return at(s, 0.1) if h < 0.06 else at(width + 0.2, h)
        if h > -0.2:
            return at(width + 0.2, -0.25)
        if (np.asarray(p["base"][:2]) - face) @ n < FOLD_ROOM:   # room to fold: back the base off
            return (-BACK_OFF / self.env.config.lin_speed, 0.0)
        return None

    # --- pick and place: a closed-loop reach from above ---

    def _face(self, point, reach):
        """Base label (v, w) facing the point at `reach` from it (a navigation's end; a pick's or place's hold)."""
        x, y, yaw = self.p["base"]
        cfg = self.env.config
        to = np.asarray(point[:2]) - [x, y]
        err = _wrap(np.arctan2(to[1], to[0]) - yaw)
        along = np.linalg.norm(to) - reach
        w = np.clip(TURN_GAIN * err / cfg.ang_speed, -SETTLE_TURN, SETTLE_TURN)
        v = 0.0 if abs(err) > SETTLE_FACING else np.clip(ALONG_GAIN * along, -SETTLE_SPEED, SETTLE_SPEED) / cfg.lin_speed
        return v, w

    def _reach_step(self, place, pt, grip, zone, base):
        """One step of the reach toward pt: every step aims FUNNEL_SLOPE x the horizontal error (at most
        FUNNEL_HEIGHT) above the point and moves the arm toward the IK solution of that aim found from the
        measured joints; within `zone` of the point the grip command is `grip`."""
        ee = self.p["ee"]
        err = pt - ee
        e_xy = np.linalg.norm(err[:2])
        height = FUNNEL_HEIGHT_FRIDGE if place == "fridge" else FUNNEL_HEIGHT
        aim = pt + [0, 0, min(height, FUNNEL_SLOPE * e_xy)]
        # reaching out from rest would sweep the forearm (and a held object) through the edge of a counter
        # higher than the folded cup, or a held object through a drawer's front: first raise the cup in place
        if place != "fridge" and e_xy > 0.15 and ee[2] < pt[2] + height - 0.03:
            aim = np.array([*ee[:2], pt[2] + height])
        # release only over the point: released farther out, the object can land on a shelf's front edge and fall off
        grip = grip if np.linalg.norm(err) < zone and (grip > 0 or e_xy < 0.03) else 0.0
        return self._arm_action(self._ik(aim, DOWN), base, grip)

    def _pick_step(self, obj, place):
        """Reach 0.5 cm above the object's top, the suction on for the last GRASP_ZONE: it takes an object up to
        3 cm away (env.GRASP_DIST), so a short reach still grasps; the grip label depends on observed distance."""
        pt = obj + [0, 0, env.OBJ_HALF + 0.005]
        return self._reach_step(place, pt, 1.0, GRASP_ZONE, self._face(obj, self._reach(place)))

    def _place_step(self, goal, place):
        """Reach for the drop point (the held object 4 cm above the goal), releasing within RELEASE_ZONE of it
        once over it, or wherever the object hangs low over the goal (an arm that cannot reach the drop point
        exactly still lets go within the success distance)."""
        p = self.p
        obj = p["objects"][p["target"]]
        drop = goal + p["ee"] - obj + [0, 0, 0.04]
        over = np.linalg.norm(obj[:2] - goal[:2]) < DROP_XY and -0.02 < obj[2] - goal[2] < 0.1
        if np.linalg.norm(drop - p["ee"]) < PLACE_TOL or over:
            return self._hold(grip=-1.0)
        return self._reach_step(place, drop, -1.0, RELEASE_ZONE, self._face(goal, self._reach(place)))

    # --- opening: take the handle, pull the drawer or swing the door, let go ---

    def _grab_handle(self, r):
        """Approach the handle along the furniture's normal, the cup pointing in: the aim stays in front
        of the handle by FUNNEL_SLOPE x the cup's off-axis error (at most 0.3 m), then 1 cm past its axis
        with the suction on for the last 6 cm, so a reach that falls a few cm short still takes it."""
        p, fridge = self.p, env.RECEPTACLES[r] == "fridge"
        out = np.array([*self._frame(self.fur["fridge" if fridge else "cabinet"])[0], 0.0])
        e = p["ee"] - p["handles"][r]
        aim = p["handles"][r] + out * min(0.3, max(FUNNEL_SLOPE * np.linalg.norm(e - (e @ out) * out), -0.01))
        base = self._pose_hold(p["poses"]["fridge_door" if fridge else "cabinet"])
        return self._arm_action(self._ik(aim, -out), base, grip=1.0 if np.linalg.norm(e) < 0.06 else 0.0)

    def _operate_handle(self, r):
        """Sec. 3: pull the drawer by backing the base away; swing the door by moving the cup along its
        arc about the hinge, DOOR_STEP ahead of where it is now."""
        p, frac = self.p, self.p["open_fraction"][r]
        th = frac * env.DOOR_RANGE
        if env.RECEPTACLES[r] != "fridge" and frac < DRAWER_DONE:     # pull: back the base away
            return self._hold(base=(-BACK_OFF / self.env.config.lin_speed, 0.0))
        if env.RECEPTACLES[r] != "fridge" or th >= DOOR_DONE:          # open: let go
            return self._hold(grip=-1.0)
        f = self.fur["fridge"]
        n, lat, face = self._frame(f)
        hinge = face + n * env.DOOR_HALF - lat * f.size[1] / 2
        dth = min(DOOR_STEP, DOOR_TARGET + 0.05 - th)
        c, s = np.cos(dth), np.sin(dth)
        rel = p["ee"][:2] - hinge                                # the door turns from lat toward n
        rot = np.array([[c, s], [-s, c]]) @ np.array([rel @ n, rel @ lat])   # (n, lat) coordinates after dth
        tgt = hinge + n * rot[0] + lat * rot[1]
        # position only: the suction holds the handle by a ball joint, and the redundant arm needs
        # its freedom to follow the arc to its end
        return self._arm_action(self._ik(np.array([*tgt, p["ee"][2]])), self._pose_hold(p["poses"]["fridge_door"]))

    def _pose_hold(self, pose):
        """Base label that holds the base on a pose against what the arm's work pushes it by."""
        x, y, yaw = self.p["base"]
        along = (np.asarray(pose[:2]) - [x, y]) @ [np.cos(yaw), np.sin(yaw)]
        cfg = self.env.config
        return (np.clip(ALONG_GAIN * along, -HOLD_SPEED, HOLD_SPEED) / cfg.lin_speed,
                np.clip(TURN_GAIN * _wrap(pose[2] - yaw) / cfg.ang_speed, -HOLD_TURN, HOLD_TURN))

    # --- navigation: a distance field to the goal on the occupancy grid, pure pursuit down it ---

    def _navigate(self, pose, face=None):
        """Drive to pose (x, y, yaw), the arm folded; once there, turn to its heading, or with
        face=(point, reach) face the point and settle at reach (what a pick or place needs)."""
        p, cfg = self.p, self.env.config
        x, y, yaw = p["base"]
        pos, goal = np.array([x, y]), np.asarray(pose[:2], float)
        dist = np.linalg.norm(goal - pos)
        touch = self._contact()
        if touch is not None:                    # pressed against the scene: back off from it
            ahead = (touch[:2] - pos) @ [np.cos(yaw), np.sin(yaw)] > 0
            return self._arm_action(env.ARM_REST, ((-BACK_OFF if ahead else BACK_OFF) / cfg.lin_speed, 0.0))
        if dist < ARRIVE:                        # there: turn to its heading, or face the point at reach
            turn = np.clip(TURN_GAIN * _wrap(pose[2] - yaw) / cfg.ang_speed, -SETTLE_TURN, SETTLE_TURN)
            return self._arm_action(env.ARM_REST, (0.0, turn) if face is None else self._face(*face))
        aim = self._lookahead(pos, goal)
        err = _wrap(np.arctan2(aim[1] - y, aim[0] - x) - yaw)
        w = np.clip(NAV_TURN_GAIN * err / cfg.ang_speed, -1, 1)
        v = 0.0 if abs(err) > NAV_FACING else np.clip(NAV_SPEED_GAIN * dist, NAV_MIN_SPEED, 1.0) * np.cos(err)
        return self._arm_action(env.ARM_REST, (v, w))

    def _contact(self):
        """A world point where the robot presses on the scene harder than CONTACT_FORCE, or None."""
        force, pos = self.env.robot_contacts()
        if not len(force) or force.max() < CONTACT_FORCE:
            return None
        return pos[np.argmax(force)].copy()

    def _lookahead(self, pos, goal):
        """The point LOOKAHEAD cells down the distance field from the base (the goal itself near it)."""
        res = self.p["grid_res"] * FIELD_POOL
        dist, nxt = self._field(goal)
        c = tuple(np.clip((pos / res).astype(int), 0, np.array(dist.shape) - 1))
        if not np.isfinite(dist[c]):                 # in an inflated or blocked cell: nearest way out
            i, j = c
            win = dist[max(i - 10, 0):i + 11, max(j - 10, 0):j + 11]
            if not np.isfinite(win).any():
                return goal
            ii, jj = np.meshgrid(np.arange(win.shape[0]) + max(i - 10, 0), np.arange(win.shape[1]) + max(j - 10, 0), indexing="ij")
            score = np.where(np.isfinite(win), win + 20.0 * np.hypot(ii - i, jj - j), np.inf)
            a = np.unravel_index(np.argmin(score), win.shape)
            return (np.array([ii[a], jj[a]]) + 0.5) * res
        for _ in range(LOOKAHEAD):
            n = nxt[c]
            if n < 0:
                return goal
            c = (n // dist.shape[1], n % dist.shape[1])
        return (np.array(c) + 0.5) * res

    def _field(self, goal):
        """Cost-to-go to the goal's cell over the base's free cells (8-connected; cells closer than NAV_CLEAR to
        an obstacle cost NAV_NEAR_COST, so a path keeps a learner room for error) and, per cell, the flat index
        of its next cell down (-1 at the goal). Cached: it depends only on layout, goal cell and open receptacles."""
        p = self.p
        g = tuple(np.clip((goal / p["grid_res"]).astype(int), 0, np.array(p["occupancy"].shape) - 1))   # fine cell
        key = (p["layout"].id, g, tuple(np.round(p["open_fraction"], 1)))
        if key not in self.fields:
            if len(self.fields) > 256:
                self.fields.clear()
            self.fields[key] = self._make_field(g)
        return self.fields[key]

    def _make_field(self, g):
        free, clear = ~self._blocked(NAV_INFLATE), ~self._blocked(NAV_CLEAR)
        i, j = g                                     # the goal may touch the inflation: free a disc
        disc = slice(max(i - 6, 0), i + 7), slice(max(j - 6, 0), j + 7)
        free[disc] |= ~self._blocked(env.ROBOT_RADIUS + 0.05, door_margin=0.0)[disc]
        clear[disc] |= free[disc]
        H, W = -(-free.shape[0] // FIELD_POOL), -(-free.shape[1] // FIELD_POOL)
        pool = lambda a: np.pad(a, ((0, H * FIELD_POOL - a.shape[0]), (0, W * FIELD_POOL - a.shape[1]))).reshape(
            H, FIELD_POOL, W, FIELD_POOL)
        free, clear = pool(free).any((1, 3)), pool(clear).all((1, 3))   # a way through; a wide berth
        cost = np.where(free, np.where(clear, 1.0, NAV_NEAR_COST), np.inf)
        dist = np.full(free.shape, np.inf)
        dist[g[0] // FIELD_POOL, g[1] // FIELD_POOL] = 0.0
        shift = lambda a, b: (slice(max(a, 0), H + min(a, 0)), slice(max(b, 0), W + min(b, 0)))
        steps = [(shift(a, b), shift(-a, -b), np.hypot(a, b)) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
        while True:                                  # Bellman-Ford sweeps until nothing improves
            best = dist.copy()
            for src, dst, l in steps:                # from the neighbour at (i + a, j + b) ...
                np.minimum(best[dst], dist[src] + l * cost[dst], out=best[dst])
            if np.array_equal(best, dist):
                break
            dist = best
        nxt, low = np.full(free.shape, -1, np.int64), np.full(free.shape, np.inf)   # steepest descent
        flat = np.arange(H * W).reshape(H, W)
        for src, dst, _ in steps:
            cand, idx = np.full(free.shape, np.inf), np.full(free.shape, -1, np.int64)
            cand[dst], idx[dst] = dist[src], flat[src]
            better = cand < np.minimum(low, dist)
            low[better], nxt[better] = cand[better], idx[better]
        return dist, nxt

    def _blocked(self, inflate, door_margin=DOOR_MARGIN):
        """Occupancy for planning: furniture and pulled drawers inflated by `inflate`, the open fridge door by
        door_margin more (a thin panel at the height of the folded arm, which sticks out 0.4 m from the base)."""
        p, res = self.p, self.p["grid_res"]
        grid = env.occupancy_grid(p["layout"], inflate=inflate)
        X, Y = np.meshgrid((np.arange(grid.shape[0]) + 0.5) * res, (np.arange(grid.shape[1]) + 0.5) * res, indexing="ij")
        for k, rec in enumerate(env.RECEPTACLES):
            frac = round(p["open_fraction"][k], 1)       # as the cache key
            if frac < 0.05:
                continue
            f = self.fur["fridge" if rec == "fridge" else "cabinet"]
            n, lat, face = self._frame(f)
            if rec == "fridge":                  # the door panel as a segment from the hinge
                th = frac * env.DOOR_RANGE
                a = face - lat * f.size[1] / 2
                b = a + f.size[1] * (n * np.sin(th) + lat * np.cos(th))
            else:                                # the pulled drawer's front edge
                a = face + n * frac * env.DRAWER_TRAVEL - lat * f.size[1] / 2
                b = a + lat * f.size[1]
            ab = b - a
            t = np.clip(((X - a[0]) * ab[0] + (Y - a[1]) * ab[1]) / (ab @ ab), 0, 1)
            grid |= np.hypot(X - a[0] - t * ab[0], Y - a[1] - t * ab[1]) < inflate + (door_margin if rec == "fridge" else 0.0)
        return grid


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


# --- command line: success by difficulty, failure reasons, steps per skill ---

def run(args):
    e = env.RearrangeEnv(perturb=args.perturb, perturb_after=args.perturb_after)
    x = Expert(e, plan=args.plan, seed=args.seed, noise=args.noise, nav_noise=args.nav_noise)
    eps = env.make_episodes(args.split, args.episodes, seed=args.seed)
    by_diff, failures, skill_steps = collections.defaultdict(list), collections.Counter(), collections.Counter()
    agree, total_steps, lengths = 0, 0, []
    t0 = time.perf_counter()
    e.timing = dict.fromkeys(e.timing, 0.0)
    for i, ep in enumerate(eps):
        obs, info = e.reset(seed=args.seed + i, options={"episode": ep})
        x.reset()
        done = False
        while not done:
            a, skill = x.act(obs)
            agree += int(skill == info["skill_gt"])
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
    args = Args(**vars(env.add_config_args(p, Args).parse_args()))
    if args.split not in env.SPLITS or args.plan not in PLANS:
        p.error(f"--split must be one of {tuple(env.SPLITS)} and --plan one of {PLANS}, got {args.split!r}, {args.plan!r}")
    run(args)


if __name__ == "__main__":
    main()
