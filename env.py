"""Rearrangement environment: a Fetch-like mobile manipulator in procedurally built apartments.

The task of the paper (Sec. 3, Appendix B), scaled to one CPU core: a robot with a planar base, a 7-DoF arm and
a suction cup must move a target object from its start to a goal; object and goal may sit in a closed drawer or
fridge, which the robot must open first. Scenes are built in code with `mujoco.MjSpec` from an integer layout id;
depth comes from ray casting (`mj_multiRay`), so no OpenGL is needed.

    python env.py --bench                 # steps/s with a breakdown (physics, depth, rest)
    python env.py --view --layout 3       # interactive viewer (needs a display)
    python env.py --xml scene.xml         # write a layout's MJCF for inspection

Public names used by the other stages: SKILLS, SKILL_IDS, RECEPTACLES, DIFFICULTIES, KINDS, OBS_MODES, STATE_LAYOUT,
STATE_DIM, state_layout, state_vector, depth_to_uint8, ACTION_DIM, ARM, BASE, GRIP, GRIP_VALUES, EnvConfig,
RearrangeEnv, Episode, make_episodes, make_layout, gym_env, add_config_args.

The paper's rule on privileged information (Sec. 3: "entirely from on-board sensing"; Sec. 4.2: the receptacle
label is "not used at test time"), stated once here: anything computed from the simulator's world state (receptacle
joints, object poses after the start, contact forces, the expert's plan) may be a training target (info["receptacle"],
info["receptacle_open"], the expert's skill), never a policy input. The policy's inputs are the robot's own senses
(depth, joints, its servo set-point, holding, egomotion) and the task's geometric specification (where the target
started, where the goal is): exactly what EnvConfig(obs="paper"), the default, gives; obs="privileged" adds
`receptacle_open`, read from the receptacle joints, for one ablation row.
"""
import argparse
import ast
import dataclasses
import inspect
import time

import mujoco
import numpy as np

# --- shared vocabulary (the later stages import these) ---

SKILLS = ("navigate", "pick", "place", "open_drawer", "open_fridge")
SKILL_IDS = {name: i for i, name in enumerate(SKILLS)}
RECEPTACLES = ("drawer_0", "drawer_1", "fridge")   # auxiliary label i = RECEPTACLES[i - 1] holds the target; 0 = none
DIFFICULTIES = ("easy", "hard", "very_hard")
KINDS = ("easy", "object_closed", "goal_closed", "very_hard")   # hard = object_closed or goal_closed
OBS_MODES = ("paper", "privileged")
PAPER_STATE = (("joint", 7), ("joint_target", 7), ("is_holding", 1), ("ee_rest", 3), ("obj_start", 3),
               ("goal", 3), ("obj_start_polar", 3), ("goal_polar", 3))
STATE_LAYOUTS = {"paper": PAPER_STATE, "privileged": PAPER_STATE + (("receptacle_open", 2),)}
STATE_LAYOUT = STATE_LAYOUTS["paper"]               # the default mode's, the recipe's
STATE_DIM = sum(n for _, n in STATE_LAYOUT)         # 30
# joint_target is not in the paper's observation, but it is the robot's own command: the expert's arm label depends
# on the servo set-point, which leads the joints by ~0.1 rad (EXPERIMENTS.md, M4). receptacle_open (obs="privileged"
# only) is world state: how open the target's and the goal's receptacles are. The expert opens a shut goal receptacle
# before the pick, which a 32 x 32 depth image cannot show from across the room nor a 15-step context remember
# (EXPERIMENTS.md R33, R40); the paper's setting learns it from memory and auxiliary targets instead (model.py).
ACTION_DIM = 10                                      # 7 arm deltas, 2 base velocities, 1 grip
ARM, BASE, GRIP = slice(0, 7), slice(7, 9), 9        # action layout
GRIP_VALUES = (-1.0, 0.0, 1.0)                       # release, keep, grasp = grip classes 0, 1, 2
TRAIN_LAYOUTS = tuple(range(0, 60))                  # Appendix B: 60 training scenes
EVAL_LAYOUTS = tuple(range(1000, 1020))              # 20 unseen evaluation scenes, ids disjoint
SPLITS = {"train": 0, "seen": 1, "unseen": 2}


def state_layout(obs_mode):
    """((name, size), ...) of the state vector in an observation mode (OBS_MODES)."""
    if obs_mode not in STATE_LAYOUTS:
        raise ValueError(f"obs mode {obs_mode!r}: expected one of {OBS_MODES}")
    return STATE_LAYOUTS[obs_mode]


def state_vector(obs, layout=STATE_LAYOUT):
    """Concatenate the non-visual observations in layout order -> float32 (sum of sizes,)."""
    return np.concatenate([np.asarray(obs[k], np.float32).reshape(n) for k, n in layout])


def depth_to_uint8(depth):
    """(H, W, 1) depth in [0, 1] -> (H, W) uint8, the storage format of the demos."""
    return np.round(np.clip(depth[..., 0], 0.0, 1.0) * 255.0).astype(np.uint8)


# --- configuration ---

@dataclasses.dataclass
class EnvConfig:
    depth_size: int = 32
    """depth image height and width in pixels (the paper: 256); 32: about 1,000 env steps/s on one core (`--bench`)"""
    depth_max: float = 5.0
    """metres mapped to depth 1.0; farther and no-hit pixels read 1.0"""
    max_steps: int = 1500
    """policy steps before truncation (the paper: 5,000 at its slower robot speeds)"""
    arm_delta: float = 0.05
    """rad per policy step for an arm action of 1.0"""
    lin_speed: float = 1.0
    """m/s of base for a linear action of 1.0"""
    ang_speed: float = 2.0
    """rad/s of base for an angular action of 1.0"""
    force_limit: float = 3000.0
    """N: an instantaneous robot-scene contact force above this ends the episode (failure)"""
    accum_force_limit: float = 200000.0
    """N summed over policy steps: accumulated robot-scene contact force that ends the episode"""
    perturb: bool = False
    """Sec. 5.4: the target's receptacle snaps shut once after it has been open for 50 steps"""
    perturb_after: int = 50
    """steps the target's receptacle must have been open before the perturbation fires"""
    skill_radius: float = 1.5
    """m: Appendix D distance threshold of the ground-truth skill rule"""
    obs: str = "paper"
    """paper: on-board sensing and the task's specification only (Sec. 3); privileged: also
    receptacle_open, read from the simulator (an ablation, never the headline)"""


PHYSICS_DT = 1.0 / 120.0          # Appendix B: PD control at 120 Hz ...
FRAME_SKIP = 4                    # ... policy at 30 Hz
OPEN_FRACTION = 0.7               # a receptacle counts as open above this fraction of its range
SUCCESS_DIST = 0.15               # Sec. 3: object within 15 cm of the goal
GRASP_DIST = 0.03                 # suction attaches when the cup is this close to an object or handle
OBJ_HALF = 0.03                   # objects are 6 cm cubes
N_OBJECTS = 3                     # 1 target + 2 distractors
ROBOT_RADIUS = 0.3
ROBOT_GROUP = 3                   # robot geoms live in group 3; ray casts exclude it
ARM_REST = np.array([0.0, -1.5, 0.0, 2.5, 0.0, 1.6, 0.0])   # folded: the wrist stays within 0.4 m of the base centre
ARM_RANGE = np.array([[-1.7, 1.7], [-1.6, 1.5], [-3.0, 3.0], [-2.5, 2.5], [-3.0, 3.0], [-2.2, 2.2], [-3.0, 3.0]])
ARM_KP = np.array([600, 600, 300, 300, 100, 100, 50])
ARM_FORCE = np.array([150, 150, 80, 80, 30, 30, 15])
GRID_RES = 0.05                   # m per occupancy cell

G = mujoco.mjtGeom
JT = mujoco.mjtJoint


# --- layouts: pure numpy, so episodes can be made without compiling a scene ---

@dataclasses.dataclass
class Furniture:
    name: str          # table_0, table_1, cabinet, fridge, obstacle_k
    kind: str          # surface, cabinet, fridge, obstacle
    center: tuple      # (x, y) of the footprint centre
    yaw: float         # local +x points out of the furniture's front, into the room
    size: tuple        # (depth along local x, width along local y, height)


@dataclasses.dataclass
class Layout:
    id: int
    room: tuple        # (width x, depth y) in metres; walls at x = 0, W and y = 0, D
    furniture: list


SURFACE_HEIGHT = (0.75, 0.85)     # table, counter
CAB_SIZE = (0.5, 0.8, 0.8)        # cabinet depth, width, height; drawers at DRAWER_Z
DRAWER_Z = (0.55, 0.25)           # drawer_0 (top), drawer_1 (bottom): base heights inside the cabinet
DRAWER_TRAVEL = 0.35
FRIDGE_SIZE = (0.6, 0.6, 1.5)     # a narrow door: its handle's arc stays within the arm's reach
FRIDGE_SHELF = 0.65               # shelf top 10 cm under the lower table: a goal's height tells fridge from table (R38)
DOOR_RANGE = 1.75                 # rad the fridge door swings open
DOOR_HALF = 0.015                 # m: half the door's thickness; its hinge axis stands this far before the face


def _local_to_world(f, p):
    c, s = np.cos(f.yaw), np.sin(f.yaw)
    return np.array([f.center[0] + c * p[0] - s * p[1], f.center[1] + s * p[0] + c * p[1]])


def make_layout(layout_id):
    """Deterministic apartment for a layout id: walls, two surfaces, a cabinet, a fridge, obstacles.
    Rejection sampling under a sub-seed until the layout is navigable, so every id is valid."""
    if layout_id not in TRAIN_LAYOUTS and layout_id not in EVAL_LAYOUTS:
        raise ValueError(f"layout id {layout_id}: expected one of {TRAIN_LAYOUTS[0]}..{TRAIN_LAYOUTS[-1]} "
                         f"(train) or {EVAL_LAYOUTS[0]}..{EVAL_LAYOUTS[-1]} (eval)")
    for attempt in range(100):
        rng = np.random.default_rng([layout_id, attempt])
        layout = _sample_layout(layout_id, rng)
        if layout is not None and _navigable(layout):
            return layout
    raise RuntimeError(f"layout {layout_id}: no navigable layout in 100 attempts")


def _sample_layout(layout_id, rng):
    W, D = rng.uniform(5.5, 7.0), rng.uniform(4.5, 6.0)
    items = [("table_0", "surface", (0.6, 1.0, SURFACE_HEIGHT[0])),
             ("table_1", "surface", (0.6, 1.2, SURFACE_HEIGHT[1])),
             ("cabinet", "cabinet", CAB_SIZE), ("fridge", "fridge", FRIDGE_SIZE)]
    order = rng.permutation(len(items))
    walls = [(0, np.pi / 2), (1, np.pi), (2, -np.pi / 2), (3, 0.0)]   # wall index, facing yaw
    used = {k: [] for k in range(4)}                                   # occupied intervals per wall
    furniture = []
    for name, kind, size in [items[i] for i in order]:
        for _ in range(50):
            wall, yaw = walls[rng.integers(4)]
            length = W if wall in (0, 2) else D
            half = size[1] / 2 + (0.5 if kind == "fridge" else 0.0)   # room for the door swing
            t = rng.uniform(0.8 + half, length - 0.8 - half) if length - 1.6 > 2 * half else None
            if t is None or any(abs(t - u) < half + h + 0.5 for u, h in used[wall]):
                continue
            used[wall].append((t, half))
            off = size[0] / 2
            center = {0: (t, off), 1: (W - off, t), 2: (t, D - off), 3: (off, t)}[wall]
            furniture.append(Furniture(name, kind, center, yaw, size))
            break
        else:
            return None
    for k in range(int(rng.integers(1, 3))):      # obstacles in the interior: a sofa or a pillar
        size = (0.5, 1.2, 0.45) if rng.random() < 0.5 else (0.3, 0.3, 1.2)
        center = (rng.uniform(1.6, W - 1.6), rng.uniform(1.6, D - 1.6))
        furniture.append(Furniture(f"obstacle_{k}", "obstacle", center, float(rng.uniform(-np.pi, np.pi)), size))
    return Layout(layout_id, (float(W), float(D)), furniture)


def occupancy_grid(layout, inflate=ROBOT_RADIUS + 0.05):
    """Boolean grid (nx, ny), True = blocked for the base centre; cell (i, j) is at ((i+.5)r, (j+.5)r)."""
    W, D = layout.room
    nx, ny = int(np.ceil(W / GRID_RES)), int(np.ceil(D / GRID_RES))
    X, Y = np.meshgrid((np.arange(nx) + 0.5) * GRID_RES, (np.arange(ny) + 0.5) * GRID_RES, indexing="ij")
    blocked = (X < inflate) | (X > W - inflate) | (Y < inflate) | (Y > D - inflate)
    for f in layout.furniture:
        c, s = np.cos(f.yaw), np.sin(f.yaw)
        lx = c * (X - f.center[0]) + s * (Y - f.center[1])       # into the furniture's frame
        ly = -s * (X - f.center[0]) + c * (Y - f.center[1])
        dx, dy = np.maximum(np.abs(lx) - f.size[0] / 2, 0), np.maximum(np.abs(ly) - f.size[1] / 2, 0)
        blocked |= np.hypot(dx, dy) < inflate
    return blocked


def interaction_poses(layout):
    """Where the base stands to work at each piece of furniture, facing it: {name: (x, y, yaw)}. Surfaces and
    the fridge shelf: in front. Drawers: a little farther, so the pulled drawer clears the base. Fridge door: to
    the side of the handle, so the door swings past."""
    poses = {}
    for f in layout.furniture:
        at = lambda x, y=0.0: (*_local_to_world(f, (x, y)), f.yaw + np.pi)   # local front point -> facing pose
        if f.kind == "surface":
            poses[f.name] = at(f.size[0] / 2 + 0.5)
        elif f.kind == "cabinet":
            poses.update(cabinet=at(f.size[0] / 2 + 0.62), cabinet_pick=at(f.size[0] / 2 + DRAWER_TRAVEL + 0.45))
        elif f.kind == "fridge":
            poses.update(fridge=at(f.size[0] / 2 + 0.55), fridge_door=at(f.size[0] / 2 + 0.95, 0.25))   # arc in reach
    return poses


def _navigable(layout):
    """Every interaction pose is free and in one connected free region covering most of the room."""
    free = ~occupancy_grid(layout)
    cells = [(int(p[0] / GRID_RES), int(p[1] / GRID_RES)) for p in interaction_poses(layout).values()]
    if any(not (0 <= i < free.shape[0] and 0 <= j < free.shape[1]) or not free[i, j] for i, j in cells):
        return False
    comp = _flood(free, cells[0])
    return all(comp[i, j] for i, j in cells) and comp.sum() > 0.6 * free.sum()


def _flood(free, start):
    comp = np.zeros_like(free)
    stack = [start]
    comp[start] = True
    while stack:
        i, j = stack.pop()
        for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
            if 0 <= a < free.shape[0] and 0 <= b < free.shape[1] and free[a, b] and not comp[a, b]:
                comp[a, b] = True
                stack.append((a, b))
    return comp


def reachable_region(layout):
    """Cells the base centre can occupy and that connect to every interaction pose."""
    free = ~occupancy_grid(layout)
    p = next(iter(interaction_poses(layout).values()))
    return _flood(free, (int(p[0] / GRID_RES), int(p[1] / GRID_RES)))


# --- episodes ---

@dataclasses.dataclass
class Episode:
    split: str
    index: int
    seed: int
    layout: int
    kind: str               # one of KINDS
    difficulty: str         # one of DIFFICULTIES
    robot_start: tuple      # (x, y, yaw)
    objects: tuple          # N_OBJECTS (x, y, z) start positions; objects[target] is the target
    object_places: tuple    # where each object starts: a surface name or a receptacle name
    target: int
    goal: tuple             # (x, y, z) goal position of the target's centre
    goal_place: str
    obj_receptacle: int     # 0 = target on an open surface, i = RECEPTACLES[i - 1] holds it
    goal_receptacle: int    # 0 = goal on an open surface, i = RECEPTACLES[i - 1] holds it


def place_position(layout, place, rng, opened=False):
    """A random resting position (x, y, z of an object's centre) on a surface or in a receptacle, in the front
    part so that the arm can reach it; in a drawer as it is closed, or pulled open (opened=True: goals)."""
    fur = {f.name: f for f in layout.furniture}
    if place.startswith("drawer"):
        f, k = fur["cabinet"], int(place[-1])
        local = (f.size[0] / 2 - rng.uniform(0.09, 0.14) + DRAWER_TRAVEL * opened, rng.uniform(-0.2, 0.2))
        z = DRAWER_Z[k] + 0.02 + OBJ_HALF
    elif place == "fridge":
        f = fur["fridge"]
        local = (f.size[0] / 2 - rng.uniform(0.12, 0.18), rng.uniform(-0.1, 0.1))
        z = FRIDGE_SHELF + OBJ_HALF
    else:
        f = fur[place]
        local = (f.size[0] / 2 - rng.uniform(0.1, 0.2), rng.uniform(-0.35, 0.35) * f.size[1] / 1.2)
        z = f.size[2] + OBJ_HALF
    return (*[float(v) for v in _local_to_world(f, local)], float(z))


def make_episodes(split, n, seed=0):
    """n deterministic episodes of a split. Episode i depends only on (split, seed, i), not on n.
    Mix (Sec. 3): 25 % easy, 50 % hard (half object-closed, half goal-closed), 25 % very hard, for every
    split; `train` and `seen` share layouts but draw from different seed streams."""
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: expected one of {tuple(SPLITS)}")
    layouts = EVAL_LAYOUTS if split == "unseen" else TRAIN_LAYOUTS
    cache, episodes = {}, []
    for i in range(n):
        rng = np.random.default_rng([SPLITS[split], seed, i])
        layout_id = int(layouts[rng.integers(len(layouts))])
        if layout_id not in cache:
            layout = make_layout(layout_id)
            cache[layout_id] = (layout, reachable_region(layout))
        layout, region = cache[layout_id]
        kind = KINDS[i % 4]
        surfaces = [f.name for f in layout.furniture if f.kind == "surface"]
        obj_place = str(rng.choice(RECEPTACLES if kind in ("object_closed", "very_hard") else surfaces))
        # object and goal never in the two drawers of one cabinet: an open drawer covers the other
        goal_choices = [p for p in (RECEPTACLES if kind in ("goal_closed", "very_hard") else surfaces)
                        if p != obj_place and not (p.startswith("drawer") and obj_place.startswith("drawer"))]
        goal_place = str(rng.choice(goal_choices))
        places = [obj_place] + [str(rng.choice(surfaces + list(RECEPTACLES))) for _ in range(N_OBJECTS - 1)]
        positions, used = [], [place_position(layout, goal_place, rng, opened=True)]
        for place in places:                   # objects at least 12 cm apart and from the goal
            for _ in range(100):
                p = place_position(layout, place, rng)
                if all(np.hypot(p[0] - q[0], p[1] - q[1]) > 0.12 or abs(p[2] - q[2]) > 0.1 for q in used):
                    break
            positions.append(p)
            used.append(p)
        cells = np.argwhere(region)
        ci, cj = cells[rng.integers(len(cells))]
        start = (float((ci + 0.5) * GRID_RES), float((cj + 0.5) * GRID_RES), float(rng.uniform(-np.pi, np.pi)))
        target = int(rng.integers(N_OBJECTS))  # the target's slot among the objects
        positions[0], positions[target] = positions[target], positions[0]
        places[0], places[target] = places[target], places[0]
        rec = lambda p: RECEPTACLES.index(p) + 1 if p in RECEPTACLES else 0
        episodes.append(Episode(
            split=split, index=i, seed=seed, layout=layout_id, kind=kind,
            difficulty={"easy": "easy", "very_hard": "very_hard"}.get(kind, "hard"),
            robot_start=start, objects=tuple(positions), object_places=tuple(places), target=target,
            goal=used[0], goal_place=goal_place, obj_receptacle=rec(obj_place), goal_receptacle=rec(goal_place)))
    return episodes


# --- scene construction with MjSpec ---

def _box(body, name, pos, half, rgba=(0.7, 0.6, 0.5, 1), **kw):
    return body.add_geom(name=name, type=G.mjGEOM_BOX, pos=list(pos), size=list(half), rgba=list(rgba), **kw)


def build_spec(layout):
    """MjSpec of one layout: room, furniture, N_OBJECTS free objects, robot, suction constraints."""
    spec = mujoco.MjSpec()
    spec.modelname = f"apartment_{layout.id}"
    spec.compiler.degree = False                      # radians everywhere
    spec.option.timestep = PHYSICS_DT
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST   # stable stiff PD servos
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.default.joint.armature = 0.05
    spec.default.geom.contype, spec.default.geom.conaffinity = 1, 3   # scene collides with all
    wb = spec.worldbody
    wb.add_light(pos=[0, 0, 3], dir=[0, 0, -1])
    W, D = layout.room
    wb.add_geom(name="floor", type=G.mjGEOM_PLANE, pos=[W / 2, D / 2, 0], size=[W / 2 + 1, D / 2 + 1, 0.1],
                rgba=[0.8, 0.8, 0.8, 1])
    for name, pos, half in [("wall_s", (W / 2, -0.05, 0.75), (W / 2 + 0.1, 0.05, 0.75)),
                            ("wall_n", (W / 2, D + 0.05, 0.75), (W / 2 + 0.1, 0.05, 0.75)),
                            ("wall_w", (-0.05, D / 2, 0.75), (0.05, D / 2, 0.75)),
                            ("wall_e", (W + 0.05, D / 2, 0.75), (0.05, D / 2, 0.75))]:
        _box(wb, name, pos, half, rgba=(0.6, 0.6, 0.7, 1))
    for f in layout.furniture:
        body = wb.add_body(name=f"{f.name}_frame", pos=[f.center[0], f.center[1], 0], quat=[np.cos(f.yaw / 2), 0, 0, np.sin(f.yaw / 2)])
        dx, dy, h = f.size[0] / 2, f.size[1] / 2, f.size[2]
        if f.kind == "surface":
            _box(body, f"{f.name}_top", (0, 0, h - 0.02), (dx, dy, 0.02))
            _box(body, f"{f.name}_base", (-dx / 2, 0, (h - 0.04) / 2), (dx / 2, dy - 0.05, (h - 0.04) / 2))   # set back: room for the base's front
        elif f.kind == "obstacle":
            _box(body, f"{f.name}_geom", (0, 0, h / 2), (dx, dy, h / 2), rgba=(0.5, 0.5, 0.4, 1))
        elif f.kind in ("cabinet", "fridge"):        # a shell open at the front ...
            pre, col = ("cab", (0.7, 0.6, 0.5, 1)) if f.kind == "cabinet" else ("fridge", (0.9, 0.9, 0.92, 1))
            for part, pos, half in [("back", (-dx + 0.02, 0, h / 2), (0.02, dy, h / 2)),
                                    ("left", (0, dy - 0.02, h / 2), (dx, 0.02, h / 2)),
                                    ("right", (0, -dy + 0.02, h / 2), (dx, 0.02, h / 2)),
                                    ("top", (0, 0, h - 0.02), (dx, dy, 0.02)), ("base", (0, 0, 0.05), (dx, dy, 0.05))]:
                _box(body, f"{pre}_{part}", pos, half, col)
            (_build_cabinet if f.kind == "cabinet" else _build_fridge)(body, dx, dy, h)   # ... then drawers or door
    for k in range(N_OBJECTS):
        ob = wb.add_body(name=f"obj_{k}", pos=[0, 0, OBJ_HALF + 2 * k])
        ob.add_freejoint(name=f"obj_{k}_free")
        ob.add_geom(name=f"obj_{k}_geom", type=G.mjGEOM_BOX, size=[OBJ_HALF] * 3, mass=0.2,
                    rgba=[0.9, 0.2, 0.2, 1] if k == 0 else [0.2, 0.6, 0.9, 1], friction=[1.0, 0.01, 0.001])
    _build_robot(spec, wb)
    for k in range(N_OBJECTS):                        # suction: one inactive weld per object, stiff: no sag
        e = spec.add_equality(name=f"suction_obj_{k}", type=mujoco.mjtEq.mjEQ_WELD, objtype=mujoco.mjtObj.mjOBJ_BODY,
                              name1="ee", name2=f"obj_{k}", active=False, solimp=[0.99, 0.999, 0.001, 0.5, 2])
        e.data[0:3] = [0, 0, 0]                       # the spec default anchor is (0, 1, 0)
    for rec in RECEPTACLES:                           # handles: a ball joint, so the door can turn
        spec.add_equality(name=f"suction_{rec}", type=mujoco.mjtEq.mjEQ_CONNECT, objtype=mujoco.mjtObj.mjOBJ_BODY,
                          name1="ee", name2=rec, active=False)
    return spec


def _build_cabinet(body, dx, dy, h):
    _box(body, "cab_mid", (0, 0, (DRAWER_Z[0] + DRAWER_Z[1] + 0.25) / 2), (dx - 0.04, dy - 0.04, 0.01))
    for k, z in enumerate(DRAWER_Z):
        dr = body.add_body(name=f"drawer_{k}", pos=[0, 0, z])
        dr.add_joint(name=f"drawer_{k}_slide", type=JT.mjJNT_SLIDE, axis=[1, 0, 0], range=[0, DRAWER_TRAVEL],
                     damping=20.0, frictionloss=15.0)   # stays open when brushed
        iw, idp = dy - 0.07, dx - 0.05               # interior half width and half depth (1 cm clear of the walls)
        col = (0.55, 0.45, 0.35, 1)
        _box(dr, f"drawer_{k}_bottom", (0, 0, 0.01), (idp, iw, 0.01), col, mass=1.0)
        _box(dr, f"drawer_{k}_front", (dx - 0.01, 0, 0.07), (0.01, dy - 0.045, 0.07), col, mass=0.5)   # low: the arm reaches over it
        _box(dr, f"drawer_{k}_backw", (-idp, 0, 0.07), (0.01, iw, 0.07), col, mass=0.3)
        for s in (1, -1):
            _box(dr, f"drawer_{k}_side{s}", (0, s * iw, 0.07), (idp, 0.01, 0.07), col, mass=0.3)
        dr.add_geom(name=f"drawer_{k}_handle", type=G.mjGEOM_CAPSULE, fromto=[dx + 0.04, -0.12, 0.08, dx + 0.04, 0.12, 0.08],
                    size=[0.015, 0, 0], rgba=[0.2, 0.2, 0.2, 1], mass=0.1)
        dr.add_site(name=f"drawer_{k}_handle_site", pos=[dx + 0.04, 0, 0.08], size=[0.01, 0, 0])


def _build_fridge(body, dx, dy, h):
    col = (0.9, 0.9, 0.92, 1)
    _box(body, "fridge_shelf", (0, 0, FRIDGE_SHELF - 0.01), (dx - 0.02, dy - 0.04, 0.01), col)
    _box(body, "fridge_shelf2", (0, 0, 1.15), (dx - 0.02, dy - 0.04, 0.01), col)
    door = body.add_body(name="fridge", pos=[dx + DOOR_HALF, -dy, 0])   # hinge on the right edge
    door.add_joint(name="fridge_hinge", type=JT.mjJNT_HINGE, axis=[0, 0, -1], range=[0, DOOR_RANGE],
                   damping=5.0, frictionloss=5.0)   # stays where it is left
    _box(door, "fridge_door", (0, dy, h / 2), (DOOR_HALF, dy, h / 2 - 0.01), col, mass=3.0)
    door.add_geom(name="fridge_handle", type=G.mjGEOM_CAPSULE, fromto=[0.06, 2 * dy - 0.08, 0.85, 0.06, 2 * dy - 0.08, 1.15],
                  size=[0.015, 0, 0], rgba=[0.2, 0.2, 0.2, 1], mass=0.1)
    door.add_site(name="fridge_handle_site", pos=[0.06, 2 * dy - 0.08, 1.0], size=[0.01, 0, 0])


def _build_robot(spec, wb):
    rob = spec.add_default("robot", spec.default)
    rob.geom.group = ROBOT_GROUP
    rob.geom.contype, rob.geom.conaffinity = 2, 1     # robot hits the scene, never itself
    rob.geom.rgba = [0.3, 0.35, 0.8, 1]
    base = wb.add_body(name="base", pos=[0, 0, 0], childclass="robot")
    for jn, jt, ax in [("base_x", JT.mjJNT_SLIDE, [1, 0, 0]), ("base_y", JT.mjJNT_SLIDE, [0, 1, 0]),
                       ("base_yaw", JT.mjJNT_HINGE, [0, 0, 1])]:
        base.add_joint(name=jn, type=jt, axis=ax, armature=0.0)
    # the base floats 1 cm above the floor: only the servos move it, furniture stops it
    base.add_geom(name="base_geom", type=G.mjGEOM_CYLINDER, pos=[0, 0, 0.2], size=[ROBOT_RADIUS, 0.19, 0], mass=60)
    base.add_geom(name="torso", type=G.mjGEOM_BOX, pos=[-0.1, 0, 0.75], size=[0.12, 0.15, 0.36], mass=15)
    base.add_camera(name="head_cam", pos=[0.0, 0, 1.3], xyaxes=[0, -1, 0, 0.5, 0, 0.866], fovy=90)
    axes = [[0, 0, 1], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0]]   # Fetch's joint order
    lens = [0.12, 0.35, 0.0, 0.32, 0.0, 0.12, 0.05]
    parent = base.add_body(name="arm_mount", pos=[0.05, 0, 0.85])
    for i in range(7):
        link = parent.add_body(name=f"link_{i}", pos=[0, 0, 0] if i == 0 else [lens[i - 1], 0, 0], gravcomp=1.0)
        link.add_joint(name=f"arm_{i}", type=JT.mjJNT_HINGE, axis=axes[i], range=list(ARM_RANGE[i]), damping=1.0)
        if lens[i] > 0:
            link.add_geom(name=f"link_{i}_geom", type=G.mjGEOM_CAPSULE, fromto=[0, 0, 0, lens[i], 0, 0],
                          size=[0.045 if i < 3 else 0.035, 0, 0], mass=1.5)
        else:                                     # roll joints: a knob, so the body has inertia
            link.add_geom(name=f"link_{i}_geom", type=G.mjGEOM_SPHERE, size=[0.045, 0, 0], mass=0.5)
        parent = link
    ee = parent.add_body(name="ee", pos=[lens[-1], 0, 0], gravcomp=1.0)
    ee.add_geom(name="cup", type=G.mjGEOM_CYLINDER, pos=[0.01, 0, 0], zaxis=[1, 0, 0], size=[0.025, 0.01, 0],
                mass=0.1, rgba=[0.1, 0.1, 0.1, 1])
    ee.add_site(name="ee_site", pos=[0.025, 0, 0], size=[0.01, 0, 0])
    for jn, kv, fr in [("base_x", 3000.0, 600), ("base_y", 3000.0, 600), ("base_yaw", 600.0, 200)]:
        a = spec.add_actuator(name=f"{jn}_vel", target=jn, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_velocity(kv=kv)               # force-limited velocity servo: contact can stop it
        a.forcerange, a.forcelimited = [-fr, fr], 1
    for i in range(7):
        a = spec.add_actuator(name=f"arm_{i}_pos", target=f"arm_{i}", trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_position(kp=float(ARM_KP[i]), dampratio=1.0)
        a.ctrlrange, a.ctrllimited = list(ARM_RANGE[i]), 1
        a.forcerange, a.forcelimited = [-ARM_FORCE[i], ARM_FORCE[i]], 1


# --- the environment ---

class RearrangeEnv:
    """Move the target object to the goal, opening drawers and the fridge where needed.

    Observation (dict of float32; frames: "base" = the robot's planar frame, x forward):

    | key             | shape     | meaning                                                     | bounds    |
    |-----------------|-----------|-------------------------------------------------------------|-----------|
    | depth           | (H, W, 1) | head camera depth / depth_max, 90 deg FoV, no hit = 1        | [0, 1]    |
    | joint           | (7,)      | arm joint angles, rad                                       | ARM_RANGE |
    | joint_target    | (7,)      | the arm servos' set-point, which the arm action moves, rad  | ARM_RANGE |
    | is_holding      | (1,)      | 1 when the cup holds an object or a handle (Habitat's grasp) | {0, 1}    |
    | ee_rest         | (3,)      | end effector minus its rest position, base frame, m         | ~[-1, 1]  |
    | obj_start       | (3,)      | target's START position minus end effector, base frame, m   | room      |
    | goal            | (3,)      | goal minus end effector, base frame, m                      | room      |
    | obj_start_polar | (3,)      | target start from the base: distance m, sin and cos of its bearing | room, [-1, 1] |
    | goal_polar      | (3,)      | goal from the base: distance m, sin and cos of its bearing  | room, [-1, 1] |
    | receptacle_open | (2,)      | obs="privileged" only: open fraction of the receptacle holding the target, of the one holding the goal; 1 on a surface | [0, 1] |

    Action (float32, shape (10,); values in range are clipped to the bounds [-1, 1]): 0-6 arm joint target deltas
    (x arm_delta rad), 7 base linear velocity forward (x lin_speed m/s), 8 base angular velocity counter-clockwise
    (x ang_speed rad/s), 9 grip in {-1, 0, 1}: -1 release, 0 keep, +1 grasp.

    Reward: the dense move-object reward of Appendix C.3, for the Decision Transformer; its terms, in
    info["reward_terms"], sum to it: approach = 2 x decrease of the end effector - target distance, until the
    target is held; carry = 2 x decrease of the target - goal distance, while it is held; pick = +1 the first time
    the target is grasped; success = +10 on success; collision = -1e-4 x robot-scene contact force (N);
    slack = -0.002 every step.

    Success: the target rests within 15 cm of the goal and is not held (terminated). Failure (terminated,
    info["failure"]): instantaneous contact force above force_limit ("collision"), or accumulated force above
    accum_force_limit ("collision_accum"). After max_steps: truncated, info["failure"] = "timeout".
    """

    def __init__(self, **kwargs):
        names = {f.name for f in dataclasses.fields(EnvConfig)}
        unknown = set(kwargs) - names
        if unknown:
            raise ValueError(f"unknown env option(s) {sorted(unknown)}; expected some of {sorted(names)}")
        self.config = EnvConfig(**kwargs)
        if not 8 <= self.config.depth_size <= 512:
            raise ValueError(f"depth_size must be in [8, 512], got {self.config.depth_size}")
        self.state_layout = state_layout(self.config.obs)    # ValueError for an unknown mode
        self._models = {}            # layout id -> (layout, model, data, ids): compiled once
        self.episode = None
        self._done = True
        n = self.config.depth_size
        f = 0.5 * n / np.tan(np.deg2rad(90) / 2)
        u, v = np.meshgrid(np.arange(n) + 0.5 - n / 2, np.arange(n) + 0.5 - n / 2)
        self._rays = np.stack([u / f, -v / f, -np.ones_like(u)], -1).reshape(-1, 3)  # camera looks down -z
        self._geomgroup = np.ones(6, np.uint8)
        self._geomgroup[ROBOT_GROUP] = 0
        self._ray_gid, self._ray_dist = np.zeros(n * n, np.int32), np.zeros(n * n)
        self.timing = {"physics": 0.0, "depth": 0.0, "rest": 0.0}

    # --- model per layout ---

    def _load_layout(self, layout_id):
        if layout_id not in self._models:
            layout = make_layout(layout_id)
            m = build_spec(layout).compile()
            d = mujoco.MjData(m)
            qadr = lambda joints: np.array([m.jnt_qposadr[m.joint(j).id] for j in joints])   # into qpos
            dadr = lambda joints: np.array([m.jnt_dofadr[m.joint(j).id] for j in joints])    # into qvel
            arm, base = [f"arm_{i}" for i in range(7)], ("base_x", "base_y", "base_yaw")
            objs, free = [f"obj_{k}" for k in range(N_OBJECTS)], [f"obj_{k}_free" for k in range(N_OBJECTS)]
            rec = ("drawer_0_slide", "drawer_1_slide", "fridge_hinge")
            ids = {
                "arm_q": qadr(arm), "arm_v": dadr(arm), "arm_act": np.array([m.actuator(f"{n}_pos").id for n in arm]),
                "base_q": qadr(base), "base_act": np.array([m.actuator(f"{n}_vel").id for n in base]),
                "obj_q": qadr(free), "obj_v": dadr(free), "obj_body": np.array([m.body(o).id for o in objs]),
                "obj_geom": np.array([m.geom(f"{o}_geom").id for o in objs]),
                "obj_eq": np.array([m.equality(f"suction_{o}").id for o in objs]),
                "rec_q": qadr(rec), "rec_v": dadr(rec), "rec_hi": np.array([DRAWER_TRAVEL, DRAWER_TRAVEL, DOOR_RANGE]),
                "rec_body": np.array([m.body(r).id for r in RECEPTACLES]),
                "rec_eq": np.array([m.equality(f"suction_{r}").id for r in RECEPTACLES]),
                "handle_geom": np.array([m.geom(f"{r}_handle").id for r in RECEPTACLES]),
                "handle_site": np.array([m.site(f"{r}_handle_site").id for r in RECEPTACLES]),
                "ee_body": m.body("ee").id, "ee_site": m.site("ee_site").id, "cup": m.geom("cup").id,
                "cam": m.camera("head_cam").id, "is_robot": m.geom_group == ROBOT_GROUP,
                "occupancy": occupancy_grid(layout), "poses": interaction_poses(layout),   # static: computed once
            }
            self._models[layout_id] = (layout, m, d, ids)
        return self._models[layout_id]

    # --- Gymnasium-style API ---

    def reset(self, seed=None, options=None):
        """Start an episode: options={"episode": Episode}, else one drawn from `train` with the seed."""
        ep = (options or {}).get("episode")
        if ep is None:
            ep = make_episodes("train", 1, seed=0 if seed is None else int(seed))[0]
        if not isinstance(ep, Episode):
            raise ValueError(f"options['episode'] must be an env.Episode, got {type(ep).__name__}")
        self.episode = ep
        self.layout, self.model, self.data, self.ids = self._load_layout(ep.layout)
        m, d, ids = self.model, self.data, self.ids
        self.np_random = np.random.default_rng(seed)
        mujoco.mj_resetData(m, d)
        d.qpos[ids["base_q"]] = ep.robot_start
        d.qpos[ids["arm_q"]] = ARM_REST
        for k in range(N_OBJECTS):
            d.qpos[ids["obj_q"][k]:ids["obj_q"][k] + 7] = [*ep.objects[k], 1, 0, 0, 0]
        d.ctrl[ids["arm_act"]] = ARM_REST
        self._arm_target = ARM_REST.copy()
        mujoco.mj_forward(m, d)
        xy, _, rot = self._base_frame()
        self._ee_rest = rot @ (d.site_xpos[ids["ee_site"]] - [*xy, 0.0])
        self._obj_start, self._goal = np.array(ep.objects[ep.target]), np.array(ep.goal)
        self._held = self._handle = -1    # index of the held object, of the grasped handle (receptacle); -1 none
        self._in_receptacle = ep.obj_receptacle   # the target counts as inside until it is picked
        self._steps, self._accum_force, self._open_steps = 0, 0.0, 0
        self._picked = self._perturbed = self._done = False
        self._prev = self._distances()
        return self._observe(), self._info(0.0, False, None, {})

    def step(self, action):
        if self._done:
            raise RuntimeError("step() called after the episode ended; call reset() first")
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (ACTION_DIM,):
            raise ValueError(f"action must have shape ({ACTION_DIM},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a}")
        if a[GRIP] not in GRIP_VALUES:
            raise ValueError(f"action[{GRIP}] (grip) must be one of {GRIP_VALUES}, got {a[GRIP]}")
        a = np.clip(a, -1.0, 1.0)
        m, d, ids, cfg = self.model, self.data, self.ids, self.config
        t0 = time.perf_counter()
        self._grip(int(a[GRIP]))
        self._arm_target = np.clip(self._arm_target + a[ARM] * cfg.arm_delta, ARM_RANGE[:, 0], ARM_RANGE[:, 1])
        d.ctrl[ids["arm_act"]] = self._arm_target
        yaw = d.qpos[ids["base_q"][2]]
        v, w = a[7] * cfg.lin_speed, a[8] * cfg.ang_speed   # differential drive: no sideways motion
        d.ctrl[ids["base_act"]] = [v * np.cos(yaw), v * np.sin(yaw), w]
        t1 = time.perf_counter()
        mujoco.mj_step(m, d, nstep=FRAME_SKIP)
        # total robot-scene normal force (N), sampled at 30 Hz: sustained pushes, not impulses
        force = float(self.robot_contacts()[0].sum()) if d.ncon else 0.0
        # positions, contacts and forces of the new state (mj_step leaves those of the last substep's
        # start): the observation, the expert and a state restored into another env then agree
        mujoco.mj_forward(m, d)
        self.timing["physics"] += time.perf_counter() - t1
        self._steps += 1
        self._accum_force += force
        self._perturb()
        dist = self._distances()
        success = self._success(dist[1])
        held_target = self._held == self.episode.target
        terms = {"approach": 0.0 if self._picked else 2.0 * (self._prev[0] - dist[0]),
                 "carry": 2.0 * (self._prev[1] - dist[1]) if held_target else 0.0, "pick": 0.0,
                 "success": 10.0 if success else 0.0, "collision": -1e-4 * force, "slack": -0.002}
        if held_target and not self._picked:
            self._picked, self._in_receptacle = True, 0
            terms["pick"] = 1.0
        self._prev = dist
        failure = None
        if force > cfg.force_limit:
            failure = "collision"
        elif self._accum_force > cfg.accum_force_limit:
            failure = "collision_accum"
        terminated = success or failure is not None
        truncated = not terminated and self._steps >= cfg.max_steps
        if truncated:
            failure = "timeout"
        self._done = terminated or truncated
        t3 = time.perf_counter()
        obs = self._observe()
        self.timing["rest"] += (t1 - t0) + (time.perf_counter() - t3)
        return obs, float(sum(terms.values())), terminated, truncated, self._info(force, success, failure, terms)

    # --- mechanics ---

    def _grip(self, cmd):
        """Suction (Appendix B): grasp welds the object or handle the cup touches; release frees it."""
        m, d, ids = self.model, self.data, self.ids
        if cmd == -1:
            if self._held >= 0:
                d.eq_active[ids["obj_eq"][self._held]] = 0
            if self._handle >= 0:
                d.eq_active[ids["rec_eq"][self._handle]] = 0
            self._held = self._handle = -1
        elif cmd == 1 and self._held < 0 and self._handle < 0:
            near = [(mujoco.mj_geomDistance(m, d, ids["cup"], int(g), GRASP_DIST, None), kind, k)
                    for kind, geoms in (("obj", ids["obj_geom"]), ("rec", ids["handle_geom"]))
                    for k, g in enumerate(geoms)]
            dist, kind, k = min(near, key=lambda c: c[0])     # the nearest object or handle, the first of equals
            if dist >= GRASP_DIST:
                return
            ee, b, eq = ids["ee_body"], ids[f"{kind}_body"][k], ids[f"{kind}_eq"][k]
            if kind == "obj":                   # weld: anchor at the cup, the object's pose relative to it
                q1inv, relpos, relquat = np.zeros(4), np.zeros(3), np.zeros(4)
                mujoco.mju_negQuat(q1inv, d.xquat[ee])
                mujoco.mju_rotVecQuat(relpos, d.xpos[b] - d.xpos[ee], q1inv)
                mujoco.mju_mulQuat(relquat, q1inv, d.xquat[b])
                m.eq_data[eq, 0:10] = np.r_[0.0, 0.0, 0.0, relpos, relquat]
                self._held = k
            else:
                p = d.site_xpos[ids["ee_site"]]     # the contact point, in both bodies' frames
                m.eq_data[eq, 0:3] = d.xmat[ee].reshape(3, 3).T @ (p - d.xpos[ee])
                m.eq_data[eq, 3:6] = d.xmat[b].reshape(3, 3).T @ (p - d.xpos[b])
                self._handle = k
            d.eq_active[eq] = 1

    def robot_contacts(self):
        """Normal forces (N) and world positions of the robot-scene contacts in the data now, the
        contacts of the cup (it must touch what it grasps) and of the held object excepted."""
        d, ids = self.data, self.ids
        g = d.contact.geom[:d.ncon]
        rob = ids["is_robot"][g]
        mask = (rob[:, 0] ^ rob[:, 1]) & (g[:, 0] != ids["cup"]) & (g[:, 1] != ids["cup"])
        if self._held >= 0:
            hg = ids["obj_geom"][self._held]
            mask &= (g[:, 0] != hg) & (g[:, 1] != hg)
        adr = d.contact.efc_address[:d.ncon]
        mask &= adr >= 0
        # elliptic cones: a contact's first constraint row is its normal force
        return np.abs(d.efc_force[adr[mask]]), d.contact.pos[:d.ncon][mask]

    def _perturb(self):
        """Sec. 5.4: the receptacle holding the target snaps shut once, after being open a while."""
        r = self.episode.obj_receptacle
        if not self.config.perturb or self._perturbed or r == 0 or self._picked:
            return
        if self.open_fraction()[r - 1] >= OPEN_FRACTION:
            self._open_steps += 1
            if self._open_steps >= self.config.perturb_after:
                self.close_receptacle(r - 1)
                self._perturbed = True

    # --- perturbation events (the Sec. 5.4 test, and collect.py's recoveries) ---

    def close_receptacle(self, k):
        """Shut RECEPTACLES[k] at once, letting go of its handle; objects in a drawer move with it."""
        m, d, ids = self.model, self.data, self.ids
        if self._handle == k:
            d.eq_active[ids["rec_eq"][k]] = 0
            self._handle = -1
        b = ids["rec_body"][k]
        rmat_old, rpos_old = d.xmat[b].reshape(3, 3).copy(), d.xpos[b].copy()
        inside = [j for j in range(N_OBJECTS) if j != self._held and self._in_drawer(j, k)]
        local = {j: rmat_old.T @ (d.xpos[ids["obj_body"][j]] - rpos_old) for j in inside}
        d.qpos[ids["rec_q"][k]] = 0.0
        d.qvel[ids["rec_v"][k]] = 0.0
        mujoco.mj_kinematics(m, d)
        for j in inside:
            q = ids["obj_q"][j]
            d.qpos[q:q + 3] = d.xpos[b] + d.xmat[b].reshape(3, 3) @ local[j]
            d.qvel[ids["obj_v"][j]:ids["obj_v"][j] + 6] = 0.0
        mujoco.mj_forward(m, d)

    def _in_drawer(self, j, k):
        """Does object j rest in drawer k (a fridge door moves nothing)?"""
        if RECEPTACLES[k] == "fridge":
            return False
        d, ids = self.data, self.ids
        b = ids["rec_body"][k]
        rel = d.xmat[b].reshape(3, 3).T @ (d.xpos[ids["obj_body"][j]] - d.xpos[b])
        return abs(rel[0]) < CAB_SIZE[0] / 2 and abs(rel[1]) < CAB_SIZE[1] / 2 and -0.02 < rel[2] < 0.15

    def drop(self):
        """Let go of whatever the cup holds."""
        self._grip(-1)
        mujoco.mj_forward(self.model, self.data)

    def push_base(self, dx, dy, dyaw):
        """Displace the base by (dx, dy) m and dyaw rad if it lands clear of the scene -> moved?"""
        m, d, ids = self.model, self.data, self.ids
        q = ids["base_q"]
        old = d.qpos[q].copy()
        d.qpos[q] = old + [dx, dy, dyaw]
        mujoco.mj_forward(m, d)
        g = d.contact.geom[:d.ncon]
        rob = ids["is_robot"][g]
        if ((rob[:, 0] ^ rob[:, 1]) & (d.contact.dist[:d.ncon] < 0)).any():
            d.qpos[q] = old
            mujoco.mj_forward(m, d)
            return False
        return True

    # --- observations and privileged state ---

    def _base_frame(self):
        """(x, y, yaw) of the base and the world -> base rotation of planar vectors."""
        x, y, yaw = self.data.qpos[self.ids["base_q"]]
        c, s = np.cos(yaw), np.sin(yaw)
        return np.array([x, y]), yaw, np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])

    def _polar(self, p, xy, yaw):
        """(distance, sin, cos) of the bearing of p from the base: a raw angle jumps by 2 pi when p
        passes behind the robot, which a network must then learn around."""
        ang = np.arctan2(p[1] - xy[1], p[0] - xy[0]) - yaw
        return np.array([np.hypot(p[0] - xy[0], p[1] - xy[1]), np.sin(ang), np.cos(ang)])

    def depth(self):
        """(H, W, 1) float32 depth image in [0, 1] by ray casting from the head camera."""
        m, d, ids = self.model, self.data, self.ids
        n, c = self.config.depth_size, ids["cam"]
        vec = self._rays @ d.cam_xmat[c].reshape(3, 3).T       # z-component 1: dist is z-depth
        mujoco.mj_multiRay(m, d, d.cam_xpos[c], vec.ravel(), self._geomgroup, 1, -1,
                           self._ray_gid, self._ray_dist, None, n * n, self.config.depth_max)
        dep = np.where(self._ray_gid < 0, 1.0, self._ray_dist / self.config.depth_max)
        return np.clip(dep, 0.0, 1.0).reshape(n, n, 1).astype(np.float32)

    def _observe(self):
        d, ids = self.data, self.ids
        t0 = time.perf_counter()
        depth = self.depth()
        self.timing["depth"] += time.perf_counter() - t0
        ee = d.site_xpos[ids["ee_site"]]
        xy, yaw, rot = self._base_frame()
        rel = rot @ np.stack([ee - [*xy, 0.0], self._obj_start - ee, self._goal - ee], 1)   # (3, 3)
        obs = {
            "depth": depth, "joint": d.qpos[ids["arm_q"]].astype(np.float32),
            "joint_target": self._arm_target.astype(np.float32),
            # Habitat's IsHoldingSensor reads grasp_mgr.is_grasped, true for an object or a handle:
            # without it a pull that lost the handle looks like one that holds it
            "is_holding": np.array([float(self._held >= 0 or self._handle >= 0)], np.float32),
            "ee_rest": (rel[:, 0] - self._ee_rest).astype(np.float32),
            "obj_start": rel[:, 1].astype(np.float32), "goal": rel[:, 2].astype(np.float32),
            "obj_start_polar": self._polar(self._obj_start, xy, yaw).astype(np.float32),
            "goal_polar": self._polar(self._goal, xy, yaw).astype(np.float32),
        }
        if self.config.obs == "privileged":     # world state as an input: the ablation only
            obs["receptacle_open"] = self._receptacle_open()
        return obs

    def _receptacle_open(self):
        """(2,) how open the receptacles are that the expert's choices rest on: the one the target is
        in (until it is picked) and the goal's; 1 for an open surface. A training target in both
        modes (info["receptacle_open"]), an input only with obs="privileged"."""
        frac = np.concatenate([[1.0], self.open_fraction()])     # index 0: no receptacle
        return frac[[self._in_receptacle, self.episode.goal_receptacle]].astype(np.float32)

    def in_view(self, point, margin=0.05):
        """Does the head camera see a world point: within its field of view and depth range, with
        nothing in front of it (a ray cast, like the depth image's)? collect.py shuts a receptacle
        only where the robot can see it happen, so that the expert's reaction can be learned."""
        m, d, c = self.model, self.data, self.ids["cam"]
        rel = np.asarray(point, float) - d.cam_xpos[c]
        v = d.cam_xmat[c].reshape(3, 3).T @ rel                  # camera frame: it looks down -z
        dist = float(np.linalg.norm(rel))
        if v[2] >= 0 or max(abs(v[0]), abs(v[1])) > -v[2] or dist > self.config.depth_max:
            return False                                          # 90 deg field of view: tan 45 = 1
        hit = mujoco.mj_ray(m, d, d.cam_xpos[c], rel / dist, self._geomgroup, 1, -1, np.zeros(1, np.int32))
        return hit < 0 or hit > dist - margin

    def open_fraction(self):
        """(3,) how open each receptacle is, in [0, 1] (RECEPTACLES order)."""
        return np.clip(self.data.qpos[self.ids["rec_q"]] / self.ids["rec_hi"], 0.0, 1.0)

    def _distances(self):
        d, ids = self.data, self.ids
        obj = d.xpos[ids["obj_body"][self.episode.target]]
        return (float(np.linalg.norm(d.site_xpos[ids["ee_site"]] - obj)), float(np.linalg.norm(obj - self._goal)))

    def _success(self, goal_dist):
        k, v = self.episode.target, self.ids["obj_v"]
        resting = np.linalg.norm(self.data.qvel[v[k]:v[k] + 3]) < 0.05
        return self._held != k and resting and goal_dist < SUCCESS_DIST

    def skill_gt(self):
        """Appendix D rule on the privileged state: the skill the task needs now. Before the pick, the next
        sub-goal is opening the goal's receptacle (it cannot be opened while the cup holds the object), then
        opening the object's, then the pick; after it, the place. The sub-goal's skill applies within
        skill_radius of its location, else navigate."""
        ep, opened = self.episode, self.open_fraction() >= OPEN_FRACTION
        base = self.data.qpos[self.ids["base_q"][:2]]
        if self._held == ep.target:
            where, rec, skill = self._goal, ep.goal_receptacle, "place"
        elif ep.goal_receptacle and not opened[ep.goal_receptacle - 1] and not self._picked:
            where, rec, skill = self._goal, ep.goal_receptacle, None
        else:
            where, rec, skill = self._obj_start, self._in_receptacle, "pick"
        if rec and not opened[rec - 1]:
            skill = "open_fridge" if RECEPTACLES[rec - 1] == "fridge" else "open_drawer"
        if np.hypot(*(where[:2] - base)) > self.config.skill_radius:
            skill = "navigate"
        return SKILL_IDS[skill]

    def receptacle_label(self):
        """Auxiliary label y^pred (Sec. 4.2): i when RECEPTACLES[i - 1] contains the target (it
        started there and is not yet picked), whether open or not; 0 when it started in the open."""
        return int(self._in_receptacle)

    def privileged(self):
        """Simulator state for the expert and the labels; never part of the observation. base: x, y, yaw;
        objects: (N_OBJECTS, 3); handles: (3, 3) in RECEPTACLES order; occupancy: blocked cells for the base centre."""
        d, ids = self.data, self.ids
        return {"base": d.qpos[ids["base_q"]].copy(), "arm": d.qpos[ids["arm_q"]].copy(),
                "arm_target": self._arm_target.copy(), "ee": d.site_xpos[ids["ee_site"]].copy(),
                "objects": d.xpos[ids["obj_body"]].copy(), "target": self.episode.target,
                "obj_start": self._obj_start.copy(), "goal": self._goal.copy(),
                "held": self._held, "handle": self._handle, "picked": self._picked,
                "handles": d.site_xpos[ids["handle_site"]].copy(), "open_fraction": self.open_fraction(),
                "obj_receptacle": self._in_receptacle, "goal_receptacle": self.episode.goal_receptacle,
                "occupancy": ids["occupancy"], "grid_res": GRID_RES, "poses": ids["poses"], "layout": self.layout,
                "episode": self.episode}

    def _info(self, force, success, failure, terms):
        return {"success": bool(success), "failure": failure, "skill_gt": self.skill_gt(),
                "receptacle": self.receptacle_label(), "receptacle_open": self._receptacle_open(),
                "reward_terms": terms, "picked": self._picked, "holding": self._held >= 0, "perturbed": self._perturbed,
                "contact_force": float(force), "steps": self._steps}


# --- Gymnasium ---

def gym_env(**config):
    """RearrangeEnv as a gymnasium.Env, with observation_space and action_space, for the tools written for
    Gymnasium (it passes gymnasium.utils.env_checker.check_env); Gymnasium is imported here only. The grip, a Box
    coordinate there, is rounded to release, keep or grasp; reset(options={"episode": Episode}) picks the episode."""
    import gymnasium
    from gymnasium import spaces

    class GymRearrangeEnv(gymnasium.Env):
        metadata = {"render_modes": []}

        def __init__(self):
            self.env = RearrangeEnv(**config)
            n, room = self.env.config.depth_size, 10.0           # m: more than any room's diagonal
            polar = (np.array([0.0, -1, -1]), np.array([room, 1, 1]))
            # the measured joints pass their limits by a few hundredths of a radian (soft limits)
            bounds = {"joint": ARM_RANGE.T + [[-0.1], [0.1]], "joint_target": ARM_RANGE.T, "is_holding": (0.0, 1.0),
                      "ee_rest": (-2.0, 2.0), "obj_start": (-room, room), "goal": (-room, room),
                      "obj_start_polar": polar, "goal_polar": polar, "receptacle_open": (0.0, 1.0)}
            box = lambda lo, hi, size: spaces.Box(np.broadcast_to(lo, (size,)).astype(np.float32),
                                                  np.broadcast_to(hi, (size,)).astype(np.float32), (size,), np.float32)
            self.observation_space = spaces.Dict({"depth": spaces.Box(0.0, 1.0, (n, n, 1), np.float32),
                                                  **{k: box(*bounds[k], size) for k, size in self.env.state_layout}})
            self.action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            return self.env.reset(seed=seed, options=options)

        def step(self, action):
            a = np.array(action, np.float32)
            a[GRIP] = GRIP_VALUES[int(np.argmin([abs(a[GRIP] - g) for g in GRIP_VALUES]))]
            return self.env.step(a)

    return GymRearrangeEnv()


# --- command line: benchmark, viewer, MJCF export ---

def bench(config, episodes=5, steps=400, seed=0):
    """Random actions over several layouts; prints steps/s and the time split."""
    e = RearrangeEnv(**dataclasses.asdict(config))
    rng = np.random.default_rng(seed)
    eps = make_episodes("train", episodes, seed=seed)
    for ep in eps:                      # compile the layouts before timing
        e.reset(seed=seed, options={"episode": ep})
    e.timing = dict.fromkeys(e.timing, 0.0)
    n, t0 = 0, time.perf_counter()
    for i, ep in enumerate(eps):
        e.reset(seed=seed + i, options={"episode": ep})
        for _ in range(steps):
            a = np.concatenate([rng.uniform(-1, 1, 9), [rng.choice(GRIP_VALUES)]]).astype(np.float32)
            _, _, term, trunc, _ = e.step(a)
            n += 1
            if term or trunc:
                break
    total = time.perf_counter() - t0
    other = total - sum(e.timing.values())
    print(f"depth {config.depth_size}x{config.depth_size}: {n / total:,.0f} steps/s over {n} steps "
          f"({1e3 * total / n:.3f} ms/step: physics {1e3 * e.timing['physics'] / n:.3f}, "
          f"depth {1e3 * e.timing['depth'] / n:.3f}, rest {1e3 * (e.timing['rest'] + other) / n:.3f})")
    return n / total


def add_config_args(parser, cls):
    """One flag per field of a config dataclass (every script's command line comes from its config):
    --name-with-dashes (or --name_with_underscores), the docstring under the field as its help,
    --flag / --no-flag for a bool (never type=bool), repeatable for a list -> the parser."""
    body = ast.parse(inspect.getsource(cls)).body[0].body
    docs = {a.target.id: b.value.value for a, b in zip(body, body[1:])
            if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant)}
    for f in dataclasses.fields(cls):
        names = [f"--{f.name.replace('_', '-')}"] + ([f"--{f.name}"] if "_" in f.name else [])
        kw = {"dest": f.name, "help": docs.get(f.name, "").replace("%", "%%")}   # argparse formats help
        if f.default_factory is list:
            parser.add_argument(*names, action="append", default=[], **kw)
        elif isinstance(f.default, bool):
            parser.add_argument(*names, action=argparse.BooleanOptionalAction, default=f.default, **kw)
        else:
            parser.add_argument(*names, type=type(f.default), default=f.default, **kw)
    return parser


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bench", action="store_true", help="print steps/s with a breakdown")
    p.add_argument("--view", action="store_true", help="open mujoco.viewer on a layout (needs a display)")
    p.add_argument("--xml", metavar="PATH", help="write the layout's MJCF to PATH")
    p.add_argument("--layout", type=int, default=0, help="layout id for --view / --xml")
    args = add_config_args(p, EnvConfig).parse_args()
    config = EnvConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(EnvConfig)})
    if args.xml:
        with open(args.xml, "w") as fh:
            fh.write(build_spec(make_layout(args.layout)).to_xml())
        print(f"wrote {args.xml}")
    if args.bench:
        bench(config)                           # another camera size: --bench --depth-size 64
    if args.view:
        import mujoco.viewer
        e = RearrangeEnv(**dataclasses.asdict(config))
        ep = next(x for x in make_episodes("train", 200) if x.layout == args.layout)
        e.reset(seed=0, options={"episode": ep})
        mujoco.viewer.launch(e.model, e.data)
    if not (args.xml or args.bench or args.view):
        p.print_help()


if __name__ == "__main__":
    main()
