"""flowmimic from Python: trajectory models, the guided controller driving the MuJoCo humanoid,
motion clips and tracking experts, over the same Rust crates as the `flowmimic` binary.

    import flowmimic
    model = flowmimic.Model("pretrained/models/fm")
    walkers = flowmimic.Controller(model, envs=4, task="joystick")   # its recommended settings
    for _ in range(90):
        out = walkers.step(flowmimic.task(joystick=(1.0, 0.0, 0.0)))
    out.states.shape                                                # (4, 165)

Tasks are plain values (`task(...)`), in the world frame (metres; each environment starts where
`Controller.start_pose(e)` says). Arrays are NumPy; the work runs without the GIL.
"""

import ctypes
import json
import os
from typing import Any, Dict, Iterable, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

MUJOCO_VERSION = "3.17.0"


def _load_mujoco() -> None:
    """Loads MuJoCo's shared library from the `mujoco` wheel (a dependency) before the native
    module, which links it; FLOWMIMIC_MUJOCO names another copy of libmujoco.so.3.17.0."""
    path = os.environ.get("FLOWMIMIC_MUJOCO")
    if path is None:
        import importlib.util

        spec = importlib.util.find_spec("mujoco")
        if spec is None or not spec.submodule_search_locations:
            raise ImportError(
                f"flowmimic needs MuJoCo {MUJOCO_VERSION}'s library: pip install mujoco=={MUJOCO_VERSION}, "
                "or set FLOWMIMIC_MUJOCO to a libmujoco.so.3.17.0"
            )
        path = os.path.join(list(spec.submodule_search_locations)[0], f"libmujoco.so.{MUJOCO_VERSION}")
    if not os.path.exists(path):
        raise ImportError(f"flowmimic: {path} does not exist (MuJoCo {MUJOCO_VERSION} is needed)")
    ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)


_load_mujoco()

from . import _flowmimic  # noqa: E402
from ._flowmimic import BODY_NAMES, CONTROL_HZ, NUM_DOFS, STATE_DIM, Clip, Expert, Model, __version__  # noqa: E402

__all__ = [
    "BODY_NAMES",
    "CONTROL_HZ",
    "NUM_DOFS",
    "STATE_DIM",
    "Clip",
    "Controller",
    "Expert",
    "Model",
    "Step",
    "cylinder",
    "generate",
    "import_bvh",
    "import_motion",
    "sample",
    "task",
    "__version__",
]

Task = Dict[str, Any]


def cylinder(x: float, y: float, radius: float, velocity: Tuple[float, float] = (0.0, 0.0), height: float = 2.0) -> Dict[str, Any]:
    """A vertical cylinder standing at (x, y) at time 0 and moving at `velocity` (m, m/s)."""
    return {"type": "cylinder", "radius": radius, "at": [x, y], "velocity": list(velocity), "height": height}


def task(
    joystick: Optional[Tuple[float, float, float]] = None,
    reach: Optional[Tuple[float, float, float]] = None,
    hand: str = "right",
    waypoint: Optional[Tuple[float, float]] = None,
    approach: bool = False,
    obstacles: Iterable[Dict[str, Any]] = (),
    weights: Sequence[float] = (1.0, 1.0, 1.0, 1.0),
) -> Task:
    """A task as `flowmimic run` builds one: a joystick command `(vx, vy, yaw_rate)` (walker's
    frame: forward, left, m/s; rad/s), a hand target `(x, y, z)` for `hand`, a pelvis waypoint
    `(x, y)` (world, m), walking up to the hand target (`approach`), obstacles (`cylinder(...)`,
    or dicts with `type` "box", `half`, `yaw`), and the weights of the joystick, heading, reach
    and waypoint costs. Nothing given: unguided walking."""
    t: Task = {"joystick": [], "weights": list(weights), "approach": approach, "obstacles": list(obstacles)}
    if joystick is not None:
        vx, vy, yaw_rate = joystick
        t["joystick"] = [{"seconds": 1e9, "vx": vx, "vy": vy, "yaw_rate": yaw_rate}]
    if reach is not None:
        t["reach"] = [hand, list(reach)]
    if waypoint is not None:
        t["waypoint"] = list(waypoint)
    return t


class Step(NamedTuple):
    """What one control step did, per environment."""

    states: np.ndarray  # [E, 165] after the step
    actions: np.ndarray  # [E, 69] executed (NaN for a fallen environment)
    fell: np.ndarray  # [E] fell in this step
    alive: np.ndarray  # [E] still standing
    touching: np.ndarray  # [E] touched an obstacle in this step


class Controller(_flowmimic.Controller):
    """The guided controller over `envs` simulated humanoids, as `flowmimic run` drives them.

    Settings not given (`nfe`, `guidance_scale`, `adaptive`, `inverse_dynamics`,
    `acceleration`, `label_scale`, `guidance_interval`, `approach`) come from the model's recommended ones for `task`
    (`walk`, `joystick`, `reach`, `waypoint`, `compose`, `play`), else the defaults."""

    def __new__(cls, model: Model, envs: int = 1, task: str = "walk", clip: Optional[Clip] = None, seed: int = 0, **settings: Any):
        known = {"nfe", "guidance_scale", "adaptive", "inverse_dynamics", "acceleration", "label_scale", "guidance_interval", "approach"}
        unknown = set(settings) - known
        if unknown:
            raise TypeError(f"unknown settings {sorted(unknown)}; known: {sorted(known)}")
        return super().__new__(cls, model, envs, task, json.dumps(settings), clip, seed)

    @property
    def settings(self) -> Dict[str, Any]:
        """The settings in force (absent ones are the defaults: NFE 5, w 10, the rest off)."""
        return {k: v for k, v in json.loads(self.settings_json).items() if v is not None}

    def step(self, tasks: Union[Task, List[Task], None] = None) -> Step:  # type: ignore[override]
        """One control step (1/30 s): one task for every environment, or one per environment."""
        if tasks is None:
            tasks = task()
        if isinstance(tasks, dict):
            tasks = [tasks] * self.envs
        return Step(*super().step([json.dumps(t) for t in tasks]))


def sample(model: Model, cond: np.ndarray, nfe: int = 5, guidance: float = 0.0, task: Optional[Task] = None, seed: int = 0) -> np.ndarray:
    """Futures `[n, future_len]` for conditionings `[n, cond_len]`, steered by `task` (read with the
    walker at the origin facing +x) at scale `guidance`."""
    cond = np.ascontiguousarray(cond, dtype=np.float32)
    return model.sample(cond, nfe, guidance, None if task is None else json.dumps(task), seed)


def import_motion(path: Union[str, os.PathLike], name: Optional[str] = None) -> Clip:
    """A BVH or DeepMimic file retargeted to the humanoid (as `flowmimic motion import`)."""
    return Clip.import_motion(os.fspath(path), name)


def import_bvh(path: Union[str, os.PathLike], name: Optional[str] = None) -> Clip:
    """A BVH motion capture (any human skeleton) retargeted to the humanoid: `import_motion`."""
    return import_motion(path, name)


def generate(name: str = "walk", **gait: float) -> Clip:
    """A procedural walk (as `flowmimic motion generate`): `speed`, `lateral`, `turn_rate`,
    `heading`, `step_frequency`, `step_height`, `arm_swing`, `duration`."""
    return Clip.generate(name, json.dumps(gait))
