"""The scenes of the paper's studies: which designs, interactions, slants and load lines are run.

Implements the study plan of formulations/puncture.md (sec. 5, worst vertex; normalisation by the
isolated scale of the same geometry, formulations/normalisation.md) and formulations/membrane.md
(sec. 8, C_f*): one :class:`Scene` per run, grouped by the paper's figures (3, 4, 6, 7, 9, 11-13).
The quick variant keeps every study but fewer designs, a 5x5 patch of fewer increments and a
coarser membrane, so the whole chain runs in a few minutes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from ..errors import InvalidDesign
from ..tiling import DESIGNS, TILINGS_OF, Design

KINDS = ("puncture", "flexure", "patch")
STUDIES = ("validation", "isolated", "interaction", "slant", "flexure_validation", "flexure", "patch")
# Slant study of the paper (Fig. 8): 60 deg towards x, the diagonal x = y, and y.
SLANT_DEG = 60.0
SLANT_DIRS = (0.0, 45.0, 90.0)
# The validation scenes of Martini et al. reproduced in the paper's Fig. 3 and Fig. 11.
VALIDATION_SLANTS = (0.0, 63.4)
QUICK_DESIGNS = (("square", "arrayed"), ("hexagon", "honeycomb"))
# The paper's patch (5x5), and the largest patch of the patch-size study (9x9; quick: 7x7).
PAPER_RINGS = 2
PATCH_RINGS = {False: 4, True: 3}


@dataclass(frozen=True)
class Scene:
    """One run of a study.

    Parameters
    ----------
    study : str
        One of ``STUDIES``.
    kind : {"puncture", "flexure", "patch"}
        ``patch``: the worst vertex of the paper's patch (``PAPER_RINGS``; read from the puncture
        scene of the same design, ``paper_run.paper_sibling``) on the patches of 1, 2, ...,
        ``rings`` rings (formulations/puncture.md sec. 7, "The study's patch sequence").
    shape, tiling, slant_deg, slant_dir_deg, gap, thickness, rings
        The design (``Design``); rings = 0 is the isolated scale (puncture only); a patch scene's
        largest patch, more than ``PAPER_RINGS``.
    interaction : str
        Puncture interaction mode ``full``, ``substrate`` or ``contact`` (paper f = 0.04).
    flex_mode : str
        Flexure mode ``scaled``, ``isolated`` or ``bare``.
    load_line : str
        Flexure load line ``x`` or ``y``.
    increments : int
        Target increments of a puncture path / plate positions of a flexure curve.
    mesh_h : float
        In-plane element size of the membrane, in L.
    """

    study: str
    kind: str
    shape: str = "square"
    tiling: str | None = None
    slant_deg: float = 0.0
    slant_dir_deg: float = 0.0
    gap: float = 0.005
    thickness: float = 1.0
    rings: int = 2
    interaction: str = "full"
    flex_mode: str = "scaled"
    load_line: str = "x"
    increments: int = 16
    mesh_h: float = 0.5

    def __post_init__(self) -> None:
        if self.study not in STUDIES:
            raise InvalidDesign("study", self.study, "{" + ", ".join(STUDIES) + "}")
        if self.kind not in KINDS:
            raise InvalidDesign("kind", self.kind, "{" + ", ".join(KINDS) + "}")
        if self.kind == "patch" and not self.rings > PAPER_RINGS:
            raise InvalidDesign("rings", self.rings, f"integers above {PAPER_RINGS} for a patch scene")
        if self.tiling is None:
            object.__setattr__(self, "tiling", TILINGS_OF.get(self.shape, ("",))[0])
        _ = self.design  # Design validates shape, tiling, slant, gap, thickness and rings

    @property
    def design(self) -> Design:
        return Design(
            self.shape, self.tiling, self.slant_deg, self.slant_dir_deg, self.gap, self.thickness, self.rings
        )

    @property
    def key(self) -> str:
        """A unique, readable identifier: study/shape-tiling/mode/slant."""
        mode = self.interaction if self.kind != "flexure" else f"{self.flex_mode}-{self.load_line}"
        ring = "iso" if self.rings == 0 and self.kind == "puncture" else f"r{self.rings}"
        slant = f"a{self.slant_deg:g}-d{self.slant_dir_deg:g}"
        return f"{self.study}/{self.shape}-{self.tiling}/{ring}/{mode}/{slant}"

    def as_dict(self) -> dict:
        return {"scene": self.key, **asdict(self)}


def _designs(quick: bool) -> tuple[tuple[str, str], ...]:
    return QUICK_DESIGNS if quick else DESIGNS


def puncture_scenes(quick: bool) -> list[Scene]:
    """Validation (Fig. 3), isolated shapes (Fig. 4), interaction modes (Fig. 6), slants (Fig. 9)."""
    inc = 6 if quick else 16
    scenes = [
        Scene("validation", "puncture", "square", "arrayed", a, 0.0, rings=r, increments=inc)
        for a in VALIDATION_SLANTS
        for r in (0, 2)
    ]
    shapes = sorted({s for s, _ in _designs(quick)}) if quick else list(TILINGS_OF)
    scenes += [Scene("isolated", "puncture", s, rings=0, increments=inc) for s in shapes]
    for shape, tiling in _designs(quick):
        scenes += [
            Scene("interaction", "puncture", shape, tiling, interaction=m, increments=inc)
            for m in ("full", "substrate", "contact")
        ]
    dirs = (45.0,) if quick else SLANT_DIRS
    for shape, tiling in _designs(quick):
        scenes += [Scene("slant", "puncture", shape, tiling, SLANT_DEG, d, increments=inc) for d in dirs]
    scenes += [
        Scene("slant", "puncture", s, None, SLANT_DEG, d, rings=0, increments=inc)
        for s in shapes
        for d in dirs
    ]
    return scenes


def patch_scenes(quick: bool) -> list[Scene]:
    """The patch-size study (not in the paper): each design of the interaction and slant studies,
    full interaction, from 3x3 to 9x9 at the worst vertex of the paper's 5x5 patch
    (formulations/puncture.md sec. 7).  The quick study keeps its unslanted designs only, to 7x7:
    its slanted 5x5 square alone takes a minute."""
    inc = 6 if quick else 16
    variants = [(0.0, 0.0)] + ([] if quick else [(SLANT_DEG, d) for d in SLANT_DIRS])
    return [
        Scene("patch", "patch", shape, tiling, a, d, rings=PATCH_RINGS[quick], increments=inc)
        for shape, tiling in _designs(quick)
        for a, d in variants
    ]


def flexure_scenes(quick: bool) -> list[Scene]:
    """Validation (Fig. 11), every design's compliance for both load lines (Fig. 12), references."""
    h, inc = (1.0, 2) if quick else (0.5, 5)
    lines = ("x", "y")
    scenes = [
        Scene(
            "flexure_validation",
            "flexure",
            "square",
            "arrayed",
            a,
            0.0,
            load_line=ln,
            increments=inc,
            mesh_h=h,
        )
        for a in VALIDATION_SLANTS
        for ln in lines
    ]
    scenes += [
        Scene("flexure", "flexure", flex_mode="bare", load_line=ln, increments=inc, mesh_h=h) for ln in lines
    ]
    shapes = sorted({s for s, _ in _designs(quick)}) if quick else list(TILINGS_OF)
    scenes += [
        Scene("flexure", "flexure", s, flex_mode="isolated", load_line=ln, increments=inc, mesh_h=h)
        for s in shapes
        for ln in lines
    ]
    dirs = (45.0,) if quick else SLANT_DIRS
    for shape, tiling in _designs(quick):
        variants = [(0.0, 0.0)] + [(SLANT_DEG, d) for d in dirs]
        scenes += [
            Scene("flexure", "flexure", shape, tiling, a, d, load_line=ln, increments=inc, mesh_h=h)
            for a, d in variants
            for ln in lines
        ]
    return scenes


def paper_scenes(quick: bool = False) -> list[Scene]:
    """Every scene of the paper's studies (quick: two designs, coarse settings), keys unique.

    >>> len({s.key for s in paper_scenes(quick=True)}) == len(paper_scenes(quick=True))
    True
    """
    return puncture_scenes(quick) + patch_scenes(quick) + flexure_scenes(quick)


def smoke_scenes() -> list[Scene]:
    """Five quick scenes through the whole chain (both kinds, the table, every figure's code path):
    the isolated square (validation and isolated studies), the 5x5 square array, the bare membrane
    and the covered one at the quick mesh.  ``qpscale paper --quick --smoke`` runs them: the
    plain-install check of .ci/run (under a minute on one core).

    >>> [s.kind for s in smoke_scenes()].count("flexure")
    2
    """
    inc, h = 6, 1.0
    return [
        Scene("validation", "puncture", "square", "arrayed", rings=0, increments=inc),
        Scene("isolated", "puncture", "square", rings=0, increments=inc),
        Scene("interaction", "puncture", "square", "arrayed", interaction="full", increments=inc),
        Scene("flexure", "flexure", flex_mode="bare", load_line="x", increments=2, mesh_h=h),
        Scene("flexure", "flexure", "square", "arrayed", load_line="x", increments=2, mesh_h=h),
    ]
