"""Type stubs of the native module (python/src/lib.rs): what an editor completes and documents."""

from typing import List, Optional, Tuple

import numpy as np
import numpy.typing as npt

STATE_DIM: int
NUM_DOFS: int
BODY_NAMES: List[str]
CONTROL_HZ: float
__version__: str

class Model:
    """A trajectory model directory (`flowmimic train` writes one; `pretrained/models/fm` ships)."""

    def __init__(self, path: str) -> None: ...
    @property
    def objective(self) -> str:
        """`fm`, `ddpm` or `meanflow`."""
    @property
    def horizon(self) -> int:
        """Predicted steps H."""
    @property
    def history(self) -> int:
        """Past states N in the conditioning."""
    @property
    def cond_len(self) -> int:
        """Length of one conditioning row (the history's states and actions interleaved)."""
    @property
    def future_len(self) -> int:
        """Length of one sampled future (H actions and states)."""
    @property
    def has_inverse_dynamics(self) -> bool: ...
    @property
    def normalisation(self) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """Mean and standard deviation of a whole window (conditioning, then future)."""
    def recommended_json(self, task: str) -> str:
        """The recommended settings for a task, as JSON."""
    def sample(
        self, cond: npt.NDArray[np.float32], nfe: int = 5, guidance: float = 0.0, task_json: Optional[str] = None, seed: int = 0
    ) -> npt.NDArray[np.float32]:
        """Futures `[n, future_len]` for conditionings `[n, cond_len]` (physical units)."""

class Controller:
    """The guided controller over simulated humanoids (use `flowmimic.Controller`)."""

    def __init__(
        self, model: Model, envs: int = 1, task: str = "walk", settings_json: Optional[str] = None, clip: Optional[Clip] = None, seed: int = 0
    ) -> None: ...
    @property
    def envs(self) -> int: ...
    @property
    def time(self) -> float:
        """Seconds since the last reset."""
    @property
    def settings_json(self) -> str: ...
    def reset(self) -> None:
        """Every environment back at its start frame of the clip."""
    def start_pose(self, e: int) -> Tuple[float, float, float]:
        """Where environment `e` starts: x, y (m) and heading (rad)."""
    def step(
        self, tasks_json: List[str]
    ) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.bool_], npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
        """One control step: states, actions, fell, alive, touching."""
    def body_positions(self) -> npt.NDArray[np.float64]:
        """World positions of the 24 bodies, `[E, 24, 3]`."""
    def planned(self) -> npt.NDArray[np.float32]:
        """What each current plan asks, `[E, 3]`: forward and left velocity (m/s) in its own heading, turn rate (rad/s)."""

class Clip:
    """A motion clip retargeted to the humanoid."""

    @staticmethod
    def load(path: str) -> Clip: ...
    @staticmethod
    def import_motion(path: str, name: Optional[str] = None) -> Clip:
        """A BVH or DeepMimic file, retargeted."""
    @staticmethod
    def generate(name: str = "walk", gait_json: str = "{}") -> Clip:
        """A procedural walk."""
    def save(self, path: str) -> None: ...
    @property
    def name(self) -> str: ...
    def __len__(self) -> int: ...
    @property
    def qpos(self) -> npt.NDArray[np.float64]:
        """`[T, 76]`: root xyz, quaternion wxyz, 69 hinge angles."""
    @property
    def body_positions(self) -> npt.NDArray[np.float64]:
        """`[T, 24, 3]` world positions of the bodies."""
    @property
    def states(self) -> npt.NDArray[np.float32]:
        """`[T, 165]` model states."""

class Expert:
    """A PPO tracking expert (a `flowmimic track train` run directory)."""

    def __init__(self, run: str) -> None: ...
    @property
    def obs_dim(self) -> int: ...
    def act(self, observations: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """Deterministic normalised actions `[n, 69]` for raw observations `[n, obs_dim]`."""

class Tracking:
    """The tracking task over `envs` humanoids stepped in Rust threads (use `flowmimic.gym`)."""

    def __init__(
        self,
        clip: Clip,
        envs: int = 1,
        kicks: bool = False,
        random_start: bool = False,
        seed: int = 0,
        observe_ahead: bool = False,
    ) -> None: ...
    @property
    def envs(self) -> int: ...
    @property
    def obs_dim(self) -> int: ...
    @property
    def clip_len(self) -> int: ...
    @property
    def frames(self) -> npt.NDArray[np.uintp]:
        """The reference frame each environment is at."""
    def reset_env(self, e: int, seed: Optional[int] = None) -> npt.NDArray[np.float32]:
        """Starts environment `e` anew; its observation."""
    def step(
        self, actions: npt.NDArray[np.float32]
    ) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
        """Observations, rewards, terminated, truncated."""
