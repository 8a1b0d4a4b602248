"""The calibration candidates: one typed table of the models a fit compares, and the records its steps share.

:data:`TABLE` lists every candidate the cross-validation knows, simplest first (the order the near-tie rule
prefers, :func:`labcal.calibration.cv.choose`). A row says what the candidate is fitted on (``base``) and which
learned term it adds (``learned``); every other name set is derived from it — the order, the networks, the
hybrid's stage-2 candidates and the ``kept`` labels a hybrid's info carries (those labels and the candidate names
are saved with a fit, so they never change spelling).

======================  ===============  =========  ===========================
name                    base             learned    hybrid ``kept`` label
======================  ===============  =========  ===========================
``nominal``             ``registered``   –          –
``local-poe``           ``nominal``      –          ``local-poe``
``hybrid+series``       ``local-poe``    series     ``local-poe+series``
``hybrid+ann``          ``local-poe``    ann        ``local-poe+ann``
``ann``                 ``registered``   ann        –
======================  ===============  =========  ===========================

Adding a candidate touches three places: its row here, how a fold fits it (:func:`labcal.calibration.cv.
fold_model`) and how it is refitted on all rows once chosen (:mod:`labcal.calibration.hybrid` for a learned term
on the identified robot, :mod:`labcal.calibration.fit` otherwise); a new user-facing method also needs its entry
in :data:`labcal.calibration.fit.METHODS`.

Example::

    >>> ORDER
    ('nominal', 'local-poe', 'hybrid+series', 'hybrid+ann', 'ann')
    >>> BY_NAME["hybrid+series"].kept, STAGE2["ann"], NETWORKS
    ('local-poe+series', 'hybrid+ann', ('hybrid+ann', 'ann'))
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, NotRequired, TypeAlias, TypedDict, TypeVar, final

from labcal.calibration.local_poe import LocalPOEInfo, RegisterInfo
from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics.poe import LocalPOEModel

if TYPE_CHECKING:  # these modules import this one for the table; the records only name their types
    from labcal.calibration.ann import ANNInfo
    from labcal.calibration.cv import CVResult
    from labcal.calibration.hybrid import HybridInfo, HybridKept
    from labcal.calibration.joint_series import SeriesInfo

T = TypeVar("T")
I = TypeVar("I", covariant=True)  # a record's info type


@dataclass(frozen=True)
class Method:
    """One row of :data:`TABLE`.

    name: the candidate's name in the cross-validation record (``FitResult.cv``, saved with a fit); base: what it
    is fitted on — "nominal" (the robot file's model), "registered" (the nominal with its tracker frame),
    "local-poe" (the identified robot); learned: the learned term it adds to the base ("series", "ann"), if any.
    """

    name: str
    base: str
    learned: str | None = None

    @property
    def network(self) -> bool:
        """It trains a network (the expensive candidates the cross-validation may prune)."""
        return self.learned == "ann"

    @property
    def hybrid(self) -> bool:
        """A learned term on the identified robot: the hybrid's stage 2."""
        return self.base == "local-poe"

    @property
    def kept(self) -> str:
        """The label a hybrid's ``info["kept"]`` gives this candidate ("local-poe+series" …)."""
        return f"local-poe+{self.learned}" if self.hybrid else self.name


TABLE: tuple[Method, ...] = (
    Method("nominal", base="registered"),
    Method("local-poe", base="nominal"),
    Method("hybrid+series", base="local-poe", learned="series"),
    Method("hybrid+ann", base="local-poe", learned="ann"),
    Method("ann", base="registered", learned="ann"),
)
BY_NAME: dict[str, Method] = {m.name: m for m in TABLE}
ORDER: tuple[str, ...] = tuple(m.name for m in TABLE)  # simplest first
NETWORKS: tuple[str, ...] = tuple(m.name for m in TABLE if m.network)
STAGE2: dict[str, str] = {m.learned: m.name for m in TABLE if m.hybrid and m.learned}  # learned term → candidate


@dataclass(frozen=True)
class Stage(Generic[I]):
    """A model fitted on every fitting row and the info its fitting function returned."""

    robot: CalibratedRobot
    info: I


class NominalInfo(TypedDict):
    """The info of method "nominal"."""

    register: RegisterInfo


@final  # final: `"loss_note" in info` tells it from ANNInfo for the type checker
class NoNetworkInfo(TypedDict):
    """The info of "ann" when too few rows could train the network; auto pops the reason once it has noted it."""

    method: str
    no_network: NotRequired[str]


# auto's info: each candidate's cross-validated error (m), local POE's info, the refitted choice's (a call: the
# saved key "local-poe" is no identifier).
AutoInfo = TypedDict(
    "AutoInfo",
    {
        "candidates": dict[str, float],
        "cv_errors": dict[str, float],
        "local-poe": LocalPOEInfo,
        "ann": NotRequired["ANNInfo | NoNetworkInfo"],
        "hybrid": NotRequired["HybridInfo | HybridKept"],
    },
)
if TYPE_CHECKING:  # FitResult.info: what the method's fitting function reports (saved with the fit)
    MethodInfo: TypeAlias = NominalInfo | LocalPOEInfo | ANNInfo | NoNetworkInfo | HybridInfo | AutoInfo


@dataclass(frozen=True)
class FitContext:
    """What every step of one :func:`labcal.calibration.fit.fit` shares: the data, the options, the timer, the notes.

    obs: all rows with their splits; fit_obs: the fitting rows; options: the method's keyword options (the
    network's for "ann", "hybrid" and "auto"); seconds and notes are filled as the steps run.
    """

    obs: Observations
    fit_obs: Observations
    nominal: LocalPOEModel
    method: str
    seed: int
    options: dict[str, Any]
    local_poe_options: dict[str, Any]
    series_options: dict[str, Any] | None
    stage2: tuple[str, ...]
    register_tool: bool
    say: Callable[[str], None]
    seconds: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def timed(self, name: str, fn: Callable[[], T]) -> T:
        """fn(), its wall time added to ``seconds[name]``."""
        t = time.perf_counter()
        out = fn()
        self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t
        return out


@dataclass(frozen=True)
class Candidates:
    """The candidates of one fit: the names that compete (simplest first), the models fitted on all rows before
    the choice — the registered nominal, local POE (None for "ann" and "nominal"), the joint series (None when it
    is not a candidate or could not be fitted) — and the cross-validation (None with too few distinct poses)."""

    names: tuple[str, ...]
    before: Stage[RegisterInfo]
    stage1: Stage[LocalPOEInfo] | None
    series: Stage[SeriesInfo] | None
    cv: CVResult | None

    def cv_error(self, name: str) -> float:
        """The candidate's cross-validated mean error (m), NaN when it was not cross-validated."""
        return self.cv.mean(name) if self.cv is not None and name in self.cv.rows else math.nan


@dataclass(frozen=True)
class Outcome(Generic[I]):
    """What a method returns: the robot, its info (saved with the fit), the method the fit reports as ``chosen``
    ("local-poe", "hybrid", "ann", "nominal"), the candidate the robot is (its name in the table) and the info of
    the network it carries, if any."""

    robot: CalibratedRobot
    info: I
    chosen: str
    candidate: str
    network: ANNInfo | NoNetworkInfo | None = None
