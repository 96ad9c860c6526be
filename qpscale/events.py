"""What happens along a loading path and at a load level, as typed records.

Implements no formulation of its own: the events are those of formulations/puncture.md (contact
changes, snaps, branches, failure, sec. 2-4) and the rescues of formulations/increment.md sec. 5
(the ordered policy of one load level).  Each record is a frozen dataclass; ``to_dict()`` gives
the JSON object of the command line's ``events`` list, with its ``kind``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, ClassVar


def _plain(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if hasattr(value, "item"):  # numpy scalars
        return value.item()
    return value


@dataclass(frozen=True)
class Event:
    """Base of every record: ``kind`` names it in the JSON output."""

    kind: ClassVar[str] = "event"

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": self.kind}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None:
                out[f.name] = _plain(value)
        return out


@dataclass(frozen=True)
class ContactChange(Event):
    """The scale pairs in contact changed between two consecutive states."""

    kind: ClassVar[str] = "contact"
    delta_between: tuple[float, float]
    pairs: tuple[tuple[int, int], ...]


@dataclass(frozen=True)
class Snap(Event):
    """A located jump of the path (puncture.md sec. 2): depth bracket, energy released, the tilt
    and the force on both sides."""

    kind: ClassVar[str] = "snap"
    delta_between: tuple[float, float]
    energy_released: float
    tilt_deg_between: tuple[float, float]
    F_between: tuple[float, float]


@dataclass(frozen=True)
class Branch(Event):
    """A located loss of stability left along its mode (puncture.md sec. 4); ``confirmed`` is
    False when no push along the mode found lower energy."""

    kind: ClassVar[str] = "branch"
    delta: float
    min_eigenvalue: float
    energy_drop: float
    confirmed: bool = True


@dataclass(frozen=True)
class Failure(Event):
    """The failure state: ``by`` is ``tilt`` (tilt = phi_c located) or ``snap`` (the tilt passes
    phi_c within a located jump; ``tilt_deg_after`` is the tilt after it)."""

    kind: ClassVar[str] = "failure"
    by: str
    delta: float
    tilt_deg: float
    tilt_deg_after: float | None = None


#: The rescues of one load level in the order they fire (formulations/increment.md sec. 5).
LEVEL_RESCUES = ("qp_retry", "stall_tighten", "other_plane_update")
#: The rescues of the path, after a level's own have failed (formulations/puncture.md sec. 2).
PATH_RESCUES = ("halve_step", "plain_iteration")


@dataclass(frozen=True)
class Rescue(Event):
    """One firing of a declared rescue: which (a name of ``LEVEL_RESCUES`` or ``PATH_RESCUES``),
    at which depth and increment, and what it changed."""

    kind: ClassVar[str] = "rescue"
    rescue: str
    delta: float
    increment: int | None = None
    detail: str = ""

    def __post_init__(self) -> None:
        if self.rescue not in LEVEL_RESCUES + PATH_RESCUES:
            raise ValueError(f"rescue {self.rescue!r} is not declared in LEVEL_RESCUES or PATH_RESCUES")
