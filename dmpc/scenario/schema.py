"""Pydantic models of the scenario file (see ``docs/scenarios.md``).

Every model forbids unknown fields and every field carries a description: the models are
the single source of the JSON Schema and of the field reference in the docs.

Checks that need more than one field (matrix shapes, definiteness, names that must exist)
raise :class:`SpecError`, a ``ValueError`` that remembers the path of the offending field
relative to the model being validated; ``dmpc.scenario.load`` turns it into the one-line
``ScenarioError`` message, e.g. ``subsystems[2].A: expected a 2x2 matrix, got 2x3``.
"""
from __future__ import annotations

import math
import numbers
import re
from collections.abc import Sequence
from typing import Annotated, Literal, Optional, Union, cast

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Discriminator, Field, Tag, WithJsonSchema, model_validator

from dmpc.bus.faults import PLANT_PROCESS
from dmpc.core.errors import DmpcError
from dmpc.core.steps import DEFAULT_METHOD, Coupling, Method, Mode, Trigger
from dmpc.estimation.kalman import DISTURBANCE_NOISE, MEASUREMENT_NOISE, STATE_NOISE
from dmpc.estimation.model import DEFAULT_KIND, KINDS, numerical_rank
from dmpc.methods import lacks

__all__ = [
    "BoxSpec", "ChainFamily", "CouplingSpec", "DesignSpec", "DiscretisationSpec", "DisturbanceSpec",
    "EstimationSpec", "FamilyCouplingSpec", "FaultsSpec", "FourTankSpec", "LabelSpec", "LinkFaultSpec",
    "MeasurementNoiseSpec", "NoiseSpec", "OptionsSpec", "PlantSpec", "PolytopeSpec",
    "RevisionBoundSpec", "Scenario", "SpecError",
    "SubsystemSpec", "SubsystemTemplate", "TerminalSpec",
]

SYM_RTOL = 1e-9
"""Relative tolerance of the symmetry check (on the largest entry's magnitude)."""
PD_RTOL = 1e-10
"""A matrix is positive definite when its smallest eigenvalue exceeds this times its largest entry."""
PLANT = PLANT_PROCESS  # reserved: the fault links name the coordinator's process so
"""The reserved name of the plant process in fault links."""
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")


class SpecError(DmpcError, ValueError):
    """A validation failure of the field at ``path`` (relative to the model being validated).

    Parameters
    ----------
    path : str
        E.g. ``"A"``, ``"input.lower[0]"``, ``"couplings[1].source"``; ``""`` is the model itself.
    message : str
        One line, without the path.
    """

    def __init__(self, path: str, message: str) -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path
        self.message = message


def _show(value: object) -> str:
    """A short one-line rendering of a user value for error messages."""
    text = repr(value).replace("\n", " ")
    return text if len(text) <= 40 else text[:37] + "..."


def _number(value: object, path: str, allow_inf: bool = False) -> float:
    """Return ``value`` as a float; reject strings, booleans, NaN and (unless allowed) infinities."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SpecError(path, f"expected a number, got {_show(value)}")
    try:
        out = float(value)
    except OverflowError:
        raise SpecError(path, f"number out of range: {_show(value)}") from None
    if math.isnan(out):
        raise SpecError(path, "expected a number, got NaN")
    if math.isinf(out) and not allow_inf:
        raise SpecError(path, f"expected a finite number, got {out}")
    return out


def _as_list(value: object) -> object:
    return value.tolist() if isinstance(value, np.ndarray) else value


def _matrix(value: object) -> list[list[float]]:
    """Validate a non-empty rectangular list of rows of finite numbers."""
    value = _as_list(value)
    if not isinstance(value, (list, tuple)) or not value:
        raise SpecError("", f"expected a matrix (a non-empty list of rows), got {_show(value)}")
    rows = []
    for r, row in enumerate(value):
        if not isinstance(row, (list, tuple)) or not row:
            raise SpecError(f"[{r}]", f"expected a row (a non-empty list of numbers), got {_show(row)}")
        rows.append([_number(x, f"[{r}][{c}]") for c, x in enumerate(row)])
    widths = sorted({len(row) for row in rows})
    if len(widths) > 1:
        raise SpecError("", f"rows have different lengths {widths}")
    return rows


def _vector(value: object, allow_inf: bool) -> list[float]:
    value = _as_list(value)
    if not isinstance(value, (list, tuple)) or not value:
        raise SpecError("", f"expected a non-empty list of numbers, got {_show(value)}")
    return [_number(x, f"[{i}]", allow_inf) for i, x in enumerate(value)]


def _name(value: object) -> str:
    """Subsystem names: strings or integers (converted), usable in Zenoh keys."""
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise SpecError("", f"expected a name (a string or an integer), got {_show(value)}")
    text = str(value)
    if not _NAME_RE.match(text):
        raise SpecError("", f"invalid name {text!r}: use letters, digits, '_', '-' and '.' "
                            "(not starting with '-' or '.')")
    return text


def _subsystem_name(value: object) -> str:
    text = _name(value)
    if text == PLANT:
        raise SpecError("", f"'{PLANT}' is reserved for the plant process")
    return text


Matrix = Annotated[list[list[float]], BeforeValidator(_matrix)]
Vector = Annotated[list[float], BeforeValidator(lambda v: _vector(v, allow_inf=False))]
BoundVector = Annotated[list[float], BeforeValidator(lambda v: _vector(v, allow_inf=True))]
_NAME_SCHEMA = WithJsonSchema({"anyOf": [{"type": "string", "pattern": _NAME_RE.pattern}, {"type": "integer"}]})
Name = Annotated[str, BeforeValidator(_subsystem_name), _NAME_SCHEMA]
Endpoint = Annotated[str, BeforeValidator(_name), _NAME_SCHEMA]
PosInt = Annotated[int, Field(strict=True, ge=1)]
PosFloat = Annotated[float, Field(strict=True, gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(strict=True, ge=0, allow_inf_nan=False)]
Probability = Annotated[float, Field(strict=True, ge=0, lt=1, allow_inf_nan=False)]


AUTO = "auto"


def _auto_or_positive(kind: type):
    """A validator of ``'auto'`` or a positive number of ``kind`` (int: >= 1; float: > 0)."""
    def check(value: object) -> object:
        if value == AUTO:
            return value
        if kind is int:
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise SpecError("", f"expected 'auto' or an integer greater than or equal to 1, got {_show(value)}")
            return value
        try:
            out = _number(value, "")
        except SpecError:
            out = float("nan")
        if not out > 0:
            raise SpecError("", f"expected 'auto' or a number greater than 0, got {_show(value)}")
        return out
    return check


AutoPosInt = Annotated[Union[Literal["auto"], int], BeforeValidator(_auto_or_positive(int)),
                       WithJsonSchema({"anyOf": [{"const": "auto"}, {"type": "integer", "minimum": 1}]})]
AutoPosFloat = Annotated[Union[Literal["auto"], float], BeforeValidator(_auto_or_positive(float)),
                         WithJsonSchema({"anyOf": [{"const": "auto"}, {"type": "number", "exclusiveMinimum": 0}]})]


def _shape(rows: list[list[float]]) -> tuple[int, int]:
    return len(rows), len(rows[0])


def check_shape(mat: list[list[float]], shape: tuple[int, int], path: str, hint: str = "") -> None:
    """Raise SpecError unless ``mat`` has ``shape``.

    Parameters
    ----------
    mat : list of list of float
        The matrix as the file gives it, a list of rows (at least one).
    shape : (int, int)
        The rows and columns expected.
    path : str
        Where ``mat`` is written, relative to the model being validated (e.g. ``"A"``).
    hint : str, optional
        Where the expected shape comes from (e.g. ``"n x n with n = 2"``), added to the message in
        parentheses; nothing when empty.
    """
    got = _shape(mat)
    if got != shape:
        tail = f" ({hint})" if hint else ""
        raise SpecError(path, f"expected a {shape[0]}x{shape[1]} matrix, got {got[0]}x{got[1]}{tail}")


def check_length(vec: Sequence[object], n: int, path: str, what: str) -> None:
    """Raise SpecError unless ``vec`` has ``n`` entries.

    Parameters
    ----------
    vec : sequence
        The list as the file gives it (numbers, or labels of states or inputs): only its length is checked.
    n : int
        The entries expected.
    path : str
        Where ``vec`` is written, relative to the model being validated.
    what : str
        What ``n`` counts and where it comes from (e.g. ``"n = 2 states, from A"``), in the message.
    """
    if len(vec) != n:
        raise SpecError(path, f"expected {n} entries ({what}), got {len(vec)}")


def check_definite(mat: list[list[float]], path: str, strict: bool) -> None:
    """Symmetric (relative tolerance ``SYM_RTOL``) and positive (semi)definite, else SpecError.

    Parameters
    ----------
    mat : list of list of float
        A square matrix as the file gives it (its shape already checked).
    path : str
        Where ``mat`` is written, relative to the model being validated.
    strict : bool
        Positive definite (smallest eigenvalue above ``PD_RTOL`` times the largest entry) when
        true, positive semidefinite (down to ``-SYM_RTOL`` times it) when false.
    """
    a = np.asarray(mat, dtype=float)
    scale = float(np.abs(a).max())
    asym = float(np.abs(a - a.T).max())
    if asym > SYM_RTOL * scale:
        raise SpecError(path, f"must be symmetric (largest |M - M^T| entry is {asym:.3g})")
    low = float(np.linalg.eigvalsh((a + a.T) / 2).min())
    if strict and not low > PD_RTOL * scale:
        raise SpecError(path, f"must be positive definite (smallest eigenvalue {low:.4g})")
    if not strict and low < -SYM_RTOL * scale:
        raise SpecError(path, f"must be positive semidefinite (smallest eigenvalue {low:.4g})")


def check_inside(x: list[float], spec: "BoxSpec | PolytopeSpec", path: str, set_path: str, owner: str = "") -> None:
    """Raise SpecError unless the point ``x`` lies in the set ``spec`` (written at ``set_path``);
    ``owner`` (e.g. "subsystem 2: ") starts the message.

    Parameters
    ----------
    x : list of float
        The point, a subsystem's start x_i(0) (one entry per coordinate of the set).
    spec : BoxSpec or PolytopeSpec
        The state set X_i.
    path : str
        Where ``x`` is written (a box's message adds the coordinate, ``path[c]``).
    set_path : str
        Where ``spec`` is written, named in the message with the bound that fails.
    owner : str, optional
        The start of the message (e.g. ``"subsystem 2: "``); none when empty.
    """
    if isinstance(spec, BoxSpec):
        for c, (value, lo, hi) in enumerate(zip(x, spec.lower, spec.upper)):
            if not lo <= value <= hi:
                side, bound = ("upper", hi) if value > hi else ("lower", lo)
                raise SpecError(f"{path}[{c}]", f"{owner}the start {value:g} is outside the state set X_i "
                                                f"({set_path}.{side}[{c}] = {bound:g})")
        return
    for r, (row, h) in enumerate(zip(spec.H, spec.h)):
        value = float(np.dot(row, x))
        if value > h:
            raise SpecError(path, f"{owner}the start is outside the state set X_i: row {r} of {set_path}.H gives "
                                  f"{value:g} > {set_path}.h[{r}] = {h:g}")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BoxSpec(_Model):
    """A box ``lower <= v <= upper`` (elementwise)."""

    lower: BoundVector = Field(description="Lower bounds, one per coordinate; `-.inf` for none. NaN is rejected.")
    upper: BoundVector = Field(description="Upper bounds, one per coordinate; `.inf` for none. Must be >= lower.")

    @model_validator(mode="after")
    def _ordered(self) -> "BoxSpec":
        check_length(self.upper, len(self.lower), "upper", "one per coordinate, like lower")
        for i, (lo, hi) in enumerate(zip(self.lower, self.upper)):
            if lo > hi:
                raise SpecError(f"lower[{i}]", f"lower bound {lo:g} is greater than upper bound {hi:g}")
        return self

    @property
    def dim(self) -> int:
        """Dimension of the box."""
        return len(self.lower)

    def origin_inside(self, path: str, point: Sequence[float] | None = None, named: str = "the origin") -> None:
        """Raise SpecError unless ``point`` (the origin when None; ``named`` in the message) is in the
        interior (``lower < point < upper``)."""
        for i, (lo, hi) in enumerate(zip(self.lower, self.upper)):
            at = 0.0 if point is None else float(point[i])
            if not lo < at:
                raise SpecError(f"{path}.lower[{i}]", f"must be < {at:g} so that the set contains {named} "
                                                      f"in its interior, got {lo:g}")
            if not hi > at:
                raise SpecError(f"{path}.upper[{i}]", f"must be > {at:g} so that the set contains {named} "
                                                      f"in its interior, got {hi:g}")


class PolytopeSpec(_Model):
    """A polytope ``H v <= h``."""

    H: Matrix = Field(description="Constraint rows, shape (rows, dimension); finite numbers.")
    h: Vector = Field(description="Right-hand sides, one per row of H; finite numbers.")

    @model_validator(mode="after")
    def _rows(self) -> "PolytopeSpec":
        check_length(self.h, len(self.H), "h", "one per row of H")
        return self

    @property
    def dim(self) -> int:
        """Dimension of the space (columns of H)."""
        return len(self.H[0])

    def origin_inside(self, path: str, point: Sequence[float] | None = None, named: str = "the origin") -> None:
        """Raise SpecError unless ``point`` (the origin when None; ``named`` in the message) is in the
        interior (``H point < h``)."""
        for i, (row, value) in enumerate(zip(self.H, self.h)):
            at = 0.0 if point is None else float(np.dot(row, point))
            if not value > at:
                times = "" if point is None else f" (row {i} of H times {named})"
                raise SpecError(f"{path}.h[{i}]", f"must be > {at:g}{times} so that the set contains {named} in its "
                                                  f"interior, got {value:g}")


def _set_kind(value: object) -> str:
    """Choose the set model: a mapping with ``H`` or ``h`` is a polytope, anything else a box."""
    if isinstance(value, PolytopeSpec) or (isinstance(value, dict) and ("H" in value or "h" in value)):
        return "polytope"
    return "box"


SET_TAGS = ("box", "polytope")
"""Union tags pydantic inserts into error locations after ``input``/``state``."""
SetSpec = Annotated[
    Union[Annotated[BoxSpec, Tag("box")], Annotated[PolytopeSpec, Tag("polytope")]],
    Discriminator(_set_kind),
]


class RevisionBoundSpec(_Model):
    """Elementwise bounds on how much a subsystem's plan may change from one step to the next."""

    state: Vector = Field(description="Bound on |z(k+t|k) - z(k+t|k-1)|, one entry per state (n_i), each >= 0.")
    input: Vector = Field(description="Bound on |v(k+t|k) - v(k+t|k-1)|, one entry per input (m_i), each >= 0.")

    @model_validator(mode="after")
    def _nonnegative(self) -> "RevisionBoundSpec":
        for field in ("state", "input"):
            for i, value in enumerate(getattr(self, field)):
                if value < 0:
                    raise SpecError(f"{field}[{i}]", f"must be >= 0, got {value:g}")
        return self


class LabelSpec(_Model):
    """The name and unit of one state or input."""

    name: str = Field(description="What the quantity is, e.g. 'position' or 'p'.")
    unit: str = Field("", description="Its unit, e.g. 'm' or 'm/s'; empty for none.")

    @property
    def label(self) -> str:
        """``name [unit]``, or the name alone without a unit."""
        return f"{self.name} [{self.unit}]" if self.unit else self.name


class OperatingPointSpec(_Model):
    """The steady state a subsystem's model is linearised around, in the plant's own units."""

    x: Vector = Field(description="The operating state, n_i entries in the plant's units.")
    u: Optional[Vector] = Field(None, description="The operating inputs, m_i entries in the plant's units; "
                                                  "omitted: zeros.")

    def inputs(self, m: int) -> list[float]:
        """``u``, or m zeros when omitted."""
        return list(self.u) if self.u is not None else [0.0] * m


class SubsystemTemplate(_Model):
    """The dynamics, cost and constraints of one subsystem (without its name and x0)."""

    A: Matrix = Field(description="A_ii, the subsystem's own state matrix, n_i x n_i.")
    B: Matrix = Field(description="B_ii, the subsystem's own input matrix, n_i x m_i.")
    Q: Matrix = Field(description="State cost weight Q_i, n_i x n_i, symmetric positive semidefinite.")
    R: Matrix = Field(description="Input cost weight R_i, m_i x m_i, symmetric positive definite.")
    input: SetSpec = Field(
        description="Input constraint set U_i: a box {lower, upper} or a polytope {H, h}, of dimension m_i. "
                    "Must contain the origin in its interior.")
    state: Optional[SetSpec] = Field(
        None, description="State constraint set X_i (box or polytope, dimension n_i, origin in its interior); "
                          "omitted or null means no state constraint.")
    K: Optional[Matrix] = Field(
        None, description="Terminal gain K_i, m_i x n_i. Required when design.gains is 'given', ignored otherwise.")
    P: Optional[Matrix] = Field(
        None, description="Terminal weight P_i, n_i x n_i, symmetric positive definite. "
                          "Required when design.gains is 'given', ignored otherwise.")
    revision_bound: Optional[RevisionBoundSpec] = Field(
        None, description="Bounds on this subsystem's plan revisions between steps. Required for every "
                          "coupling source when options.tube is 'robust' (they bound the neighbours' W_i).")
    states: Optional[list[LabelSpec]] = Field(
        None, description="Names and units of the states, one {name, unit} per state (n_i entries), used in "
                          "tables, figures and results; omitted: x1, x2, ...")
    inputs: Optional[list[LabelSpec]] = Field(
        None, description="Names and units of the inputs, one {name, unit} per input (m_i entries); omitted: "
                          "u1, u2, ...")
    C: Optional[Matrix] = Field(
        None, description="What the plant measures, y_i = C x_i: p_i x n_i with independent rows (p_i <= n_i). "
                          "Omitted: the identity, every state measured (y_i = x_i). Anything else needs "
                          "'estimation' (the agents then estimate the states they are not given).")
    outputs: Optional[list[LabelSpec]] = Field(
        None, description="Names and units of the outputs, one {name, unit} per row of C (p_i entries); omitted: "
                          "the states' names when C is omitted (or the identity), else y1, y2, ...")
    operating_point: Optional[OperatingPointSpec] = Field(
        None, description="The steady state the model is a linearisation around, in the plant's own units "
                          "(levels in m, flows in m^3/h): {x: [n_i], u: [m_i]}. Given, x0, the bounds of 'state' "
                          "and 'input' and every setpoint are in the plant's units too, the sets must contain the "
                          "operating point (not the origin) in their interior, and the records are in the "
                          "plant's units; A, B, Q, R and the couplings stay the model's, in deviations "
                          "(x - operating_point.x, u - operating_point.u). Omitted: the plant's units are the "
                          "model's (the operating point is the origin).")

    @property
    def n(self) -> int:
        """Number of states n_i."""
        return len(self.A)

    @property
    def m(self) -> int:
        """Number of inputs m_i."""
        return len(self.B[0])

    @property
    def p(self) -> int:
        """Number of measured outputs p_i (n_i when C is omitted)."""
        return self.n if self.C is None else len(self.C)

    def output_labels(self) -> list[LabelSpec]:
        """The outputs' names and units: ``outputs``, else the states' (``states``, or x1, x2, ...) when C
        is omitted or the identity, else y1, y2, ..."""
        if self.outputs is not None:
            return list(self.outputs)
        if self.measures_state:
            return list(self.states) if self.states is not None else [LabelSpec(name=f"x{j + 1}")
                                                                       for j in range(self.n)]
        return [LabelSpec(name=f"y{r + 1}") for r in range(self.p)]

    def state_rows(self) -> dict[int, int]:
        """The outputs that are a state alone: output row r -> state j where row r of C is the unit vector
        e_j (every state, r = j, when C is omitted)."""
        if self.C is None:
            return {j: j for j in range(self.n)}
        out = {}
        for r, row in enumerate(self.C):
            nonzero = [j for j, v in enumerate(row) if v != 0.0]
            if len(nonzero) == 1 and row[nonzero[0]] == 1.0:
                out[r] = nonzero[0]
        return out

    @property
    def measures_state(self) -> bool:
        """True when C is omitted or the identity: the outputs are the states, in order."""
        return self.C is None or (len(self.C) == self.n and self.state_rows() == {j: j for j in range(self.n)})

    @model_validator(mode="after")
    def _consistent(self) -> "SubsystemTemplate":
        n = len(self.A)
        check_shape(self.A, (n, n), "A", "A must be square")
        if len(self.B) != n:
            raise SpecError("B", f"expected {n} rows (n = {n} states, from A), got {len(self.B)}")
        m = self.m
        check_shape(self.Q, (n, n), "Q", f"n x n with n = {n}")
        check_definite(self.Q, "Q", strict=False)
        check_shape(self.R, (m, m), "R", f"m x m with m = {m} inputs, from B")
        check_definite(self.R, "R", strict=True)
        op = self.operating_point
        if op is not None:
            check_length(op.x, n, "operating_point.x", f"n = {n} states, from A")
            if op.u is not None:
                check_length(op.u, m, "operating_point.u", f"m = {m} inputs, from B")
        _check_set(self.input, m, "input", f"m = {m} inputs, from B", None if op is None else op.inputs(m))
        if self.state is not None:
            _check_set(self.state, n, "state", f"n = {n} states, from A", None if op is None else op.x)
        if self.K is not None:
            check_shape(self.K, (m, n), "K", "m x n")
        if self.P is not None:
            check_shape(self.P, (n, n), "P", "n x n")
            check_definite(self.P, "P", strict=True)
        if self.revision_bound is not None:
            check_length(self.revision_bound.state, n, "revision_bound.state", f"n = {n} states")
            check_length(self.revision_bound.input, m, "revision_bound.input", f"m = {m} inputs")
        if self.states is not None:
            check_length(self.states, n, "states", f"n = {n} states, from A")
        if self.inputs is not None:
            check_length(self.inputs, m, "inputs", f"m = {m} inputs, from B")
        if self.C is not None:
            _check_measurements(self.C, n)
        if self.outputs is not None:
            where = f"p = {self.p} outputs, the rows of C" if self.C is not None else \
                f"p = n = {n} outputs: C is omitted, so every state is measured"
            check_length(self.outputs, self.p, "outputs", where)
        return self


def _check_measurements(C: list[list[float]], n: int) -> None:
    """C (p x n): n columns, and independent rows (rank p), else SpecError at ``C``."""
    if len(C[0]) != n:
        raise SpecError("C", f"expected {n} columns (n = {n} states, from A), got {len(C[0])}")
    p = len(C)
    if p > n:
        raise SpecError("C", f"expected at most {n} rows (independent outputs of n = {n} states), got {p}")
    rank = numerical_rank(np.asarray(C, dtype=float))
    if rank < p:
        raise SpecError("C", f"its {p} rows must be independent, but its rank is {rank}: an output that is zero or a "
                             "combination of the others measures nothing new; remove it")


def _check_set(spec: BoxSpec | PolytopeSpec, dim: int, path: str, what: str,
               operating: list[float] | None = None) -> None:
    if isinstance(spec, BoxSpec):
        check_length(spec.lower, dim, f"{path}.lower", what)
    elif spec.dim != dim:
        raise SpecError(f"{path}.H", f"expected {dim} columns ({what}), got {spec.dim}")
    if operating is None:
        spec.origin_inside(path)
    else:
        spec.origin_inside(path, operating, f"the operating point (operating_point.{'u' if path == 'input' else 'x'})")


class _Named(_Model):
    name: Name = Field(
        description="The subsystem's unique id (integers are converted to strings): used in couplings, "
                    "graph, message keys and records. Letters, digits, '_', '-', '.'; 'plant' is reserved.")


class SubsystemSpec(SubsystemTemplate, _Named):
    """One subsystem: a template plus its name and initial state."""

    x0: Vector = Field(description="Initial state x_i(0), n_i entries.")

    @model_validator(mode="after")
    def _x0_length(self) -> "SubsystemSpec":
        check_length(self.x0, self.n, "x0", f"n = {self.n} states, from A")
        if self.state is not None:
            check_inside(self.x0, self.state, "x0", "state", f"subsystem {self.name}: ")
        return self


class CouplingSpec(_Model):
    """Dynamic coupling: ``x_target(k+1) += A x_source(k) + B u_source(k)``."""

    target: Name = Field(description="Name of the subsystem that is influenced (i in A_ij).")
    source: Name = Field(description="Name of the influencing subsystem (j in A_ij), different from target.")
    A: Matrix = Field(description="A_ij, n_target x n_source.")
    B: Optional[Matrix] = Field(None, description="B_ij, n_target x m_source; omitted or null means zeros.")


class FamilyCouplingSpec(_Model):
    """The coupling applied in both directions between neighbours of a generated chain."""

    A: Matrix = Field(description="A_ij between chain neighbours, n x n (n of the template).")
    B: Optional[Matrix] = Field(None, description="B_ij between chain neighbours, n x m; omitted or null means zeros.")


class ChainFamily(_Model):
    """M copies of one subsystem named "1".."M", coupled along a chain 1-2-...-M."""

    kind: Literal["chain"] = Field(description="Family kind; only 'chain' exists.")
    M: PosInt = Field(description="Number of subsystems (>= 1), named \"1\"..\"M\".")
    subsystem: SubsystemTemplate = Field(description="The subsystem every member copies (no name, no x0).")
    x0_cycle: list[Vector] = Field(
        min_length=1, description="Initial states used cyclically: subsystem i (0-based) starts at "
                                  "x0_cycle[i % len(x0_cycle)]. Each entry has n entries.")
    coupling: FamilyCouplingSpec = Field(
        description="Coupling applied in both directions between subsystems i and i+1.")

    @model_validator(mode="after")
    def _consistent(self) -> "ChainFamily":
        n, m = self.subsystem.n, self.subsystem.m
        for i, x0 in enumerate(self.x0_cycle):
            check_length(x0, n, f"x0_cycle[{i}]", f"n = {n} states of the template")
            if self.subsystem.state is not None:
                check_inside(x0, self.subsystem.state, f"x0_cycle[{i}]", "subsystem.state")
        check_shape(self.coupling.A, (n, n), "coupling.A", "n x n of the template")
        if self.coupling.B is not None:
            check_shape(self.coupling.B, (n, m), "coupling.B", "n x m of the template")
        return self

    def members(self) -> list[SubsystemSpec]:
        """The generated subsystems "1".."M"."""
        fields = {k: getattr(self.subsystem, k) for k in SubsystemTemplate.model_fields}
        return [SubsystemSpec.model_construct(name=str(i + 1), x0=list(self.x0_cycle[i % len(self.x0_cycle)]),
                                              **fields) for i in range(self.M)]

    def couplings(self) -> list[CouplingSpec]:
        """Both directions between i and i+1, in the order (1<-2, 2<-1, 2<-3, 3<-2, ...)."""
        out = []
        for i in range(1, self.M):
            for target, source in ((i, i + 1), (i + 1, i)):
                out.append(CouplingSpec.model_construct(target=str(target), source=str(source),
                                                        A=self.coupling.A, B=self.coupling.B))
        return out


class DesignSpec(_Model):
    """How the terminal gains K_i and weights P_i are obtained, and what the design checks."""

    gains: Literal["lmi", "lqr", "given"] = Field(
        "lmi", description="'lmi': block-diagonal LMI maximising log det P^-1; 'lqr': per-subsystem DARE, "
                           "verified on the coupled system; 'given': K and P from each subsystem, verified.")
    check_start: bool = Field(
        True, description="Refuse a start x(0) that is infeasible for the centralised problem at the given horizon "
                          "with the method's terminal set at k = 0 (one LP; the error names the smallest feasible "
                          "horizon). false runs it anyway: the run's verdict then reports what happened.")


class TerminalSpec(_Model):
    """The initial terminal box ``||x_i(N) - alpha_i(0)||_inf <= beta(0)``."""

    alpha0: Optional[dict[Name, Vector]] = Field(
        None, description="Initial box centres alpha_i(0) by subsystem name (n_i entries each); "
                          "subsystems not listed start at zeros.")
    beta0: AutoPosFloat = Field(
        "auto", description="Initial box radius beta(0) > 0; must not exceed sigma(alpha(0)). 'auto': 0.9 sigma(alpha(0)), "
                            "the largest box around alpha(0) inside X^f less a margin from its boundary.")


class OptionsSpec(_Model):
    """Algorithm and runtime options."""

    coupling: Coupling = Field(
        "feedforward", description="'feedforward': predictions include the neighbours' assumed trajectories; "
                                   "'nominal': the paper's decoupled model (not recursively feasible in general).")
    tube: Literal["none", "robust"] = Field(
        "none", description="'none': no constraint tightening; 'robust': tighten by the error tube built from "
                            "the neighbours' revision bounds.")
    iterations: PosInt = Field(1, description="Jacobi rounds per step (plans exchanged and re-solved), >= 1.")
    tolerance: PosFloat = Field(1e-9, description="Jacobi stops early when the largest plan change is below this.")
    initial_iterations: PosInt = Field(200, description="Maximum Jacobi rounds at k = 0 (iterate to convergence).")
    initial_tolerance: PosFloat = Field(1e-9, description="Jacobi convergence tolerance at k = 0.")
    cooperative_step: Literal["line", "equal"] = Field(
        "line", description="tv-box-coop: how a round combines the agents' proposals. 'line': every proposal taken "
                            "with the weight s in [1/M, 1] of least cost that keeps every constraint (never worse than "
                            "'equal'); 'equal': weights 1/M (Stewart et al. 2010). Unused by the other methods.")
    method: Method = Field(
        DEFAULT_METHOD, description="Control method. 'tv-box': the paper's time-varying terminal boxes; 'tv-box-opt': the "
                              "same with alpha(0), beta(0) = sigma(alpha(0)) chosen by the centralised QP at k = 0; "
                              "'tv-box-coop': cooperative DMPC, each agent minimising the cost of every subsystem its "
                              "inputs reach, with time-varying terminal boxes; "
                              "'fixed-box': the boxes held at alpha(0), beta(0); 'ellipsoid': terminal ellipsoids "
                              "x_i' P_i x_i <= r at the static common level (imposed through inscribed polytopes); "
                              "'ellipsoid-adaptive': the same with levels r_i(k+1) = r_i(k) + eta' Gamma_i eta; "
                              "'centralized': one QP over the whole system with X^f as terminal set (around the "
                              "target with setpoints), no agents (the optimality reference).")
    mode: Mode = Field(
        "lockstep", description="'lockstep': advance as soon as all plans are in; 'realtime': advance every dt.")
    dt: PosFloat = Field(0.1, description="Seconds per step in realtime mode.")
    deadline: Optional[PosFloat] = Field(
        None, description="Seconds an agent has to deliver its plan; null means wait forever in lockstep "
                          "and dt in realtime. A late plan counts as missed (fallback applied).")
    trigger: Trigger = Field(
        "always", description="When an agent solves its QP: 'always' (every step), or 'event': it keeps its shifted "
                              "plan, sending no plan, while the plan still holds (docs/algorithm.md, \"Event-triggered "
                              "DMPC\"); with the methods tv-box and tv-box-opt and one Jacobi round per step.")
    trigger_threshold: PerSubsystem = Field(
        1e-6, description="trigger: event: the largest prediction error ||x_i(k) - z_i(k|k-1)||_inf (in the states' "
                          "units) for which an agent keeps its plan; one number, or a map subsystem name -> number "
                          "(the others 1e-6).")
    trigger_cost: PerSubsystem = Field(
        1e-3, description="trigger: event: the most an agent's predicted cost J_i may exceed the best the solve could "
                          "find for it to keep its plan (the cost's units); one number, or a map subsystem name -> "
                          "number (the others 1e-3). 0: keep only where the plan is optimal as it stands.")
    trigger_max_keep: Optional[PosInt] = Field(
        None, description="trigger: event: the most consecutive steps an agent keeps its plan; null: no limit.")
    setpoint_margin: Annotated[float, Field(strict=True, gt=0, lt=1, allow_inf_nan=False)] = Field(
        0.05, description="Setpoint targets keep this fraction of the way from the origin to every finite bound of "
                          "X_i and U_i free (in (0, 1)): a request closer to a bound is tracked as near as that allows "
                          "(docs/algorithm.md, \"Setpoints\").")


def _per_subsystem(value: object) -> object:
    """A non-negative number, or a map subsystem name -> non-negative number."""
    value = _as_list(value)
    if isinstance(value, dict):
        out = {}
        for key, v in value.items():
            number = _number(v, f".{key}")
            if number < 0:
                raise SpecError(f".{key}", f"expected a number >= 0, got {_show(v)}")
            out[_subsystem_name(key)] = number
        return out
    number = _number(value, "")
    if number < 0:
        raise SpecError("", f"expected a number >= 0, got {_show(value)}")
    return number


PerSubsystem = Annotated[Union[float, dict[str, float]], BeforeValidator(_per_subsystem)]


def _per_subsystem_vector(value: object) -> object:
    """A number >= 0, or a map subsystem name -> a list of numbers >= 0."""
    value = _as_list(value)
    if not isinstance(value, dict):
        return _per_subsystem(value)
    out = {}
    for key, entries in value.items():
        try:
            vec = _vector(entries, allow_inf=False)
        except SpecError as exc:
            raise SpecError(f".{key}{exc.path}", exc.message) from None
        for c, number in enumerate(vec):
            if number < 0:
                raise SpecError(f".{key}[{c}]", f"expected a number >= 0, got {number:g}")
        out[_subsystem_name(key)] = vec
    return out


PerSubsystemVector = Annotated[Union[float, dict[str, list[float]]], BeforeValidator(_per_subsystem_vector)]


def _components(value: object) -> object:
    """Setpoint components: a list of numbers and nulls, or a map state name -> number (or null)."""
    value = _as_list(value)
    if isinstance(value, dict):
        return {str(key): None if v is None else _number(v, f".{key}") for key, v in value.items()}
    if isinstance(value, (list, tuple)) and value:
        return [None if v is None else _number(v, f"[{c}]") for c, v in enumerate(value)]
    raise SpecError("", f"expected a list of numbers and nulls, or a map name -> number, got {_show(value)}")


Components = Annotated[Union[list[Optional[float]], dict[str, Optional[float]]], BeforeValidator(_components)]


def _setpoint_time(value: object) -> float:
    out = _number(value, "")
    if out < 0:
        raise SpecError("", f"expected a step or a time >= 0, got {_show(value)}")
    return out


class SetpointSpec(_Model):
    """One entry of the setpoint schedule: from ``at`` on, subsystem ``subsystem`` asks for ``x`` or
    ``y`` (and ``u``); the latest entry of a subsystem at or before a step holds there."""

    at: Annotated[float, BeforeValidator(_setpoint_time)] = Field(
        description="The step from which the entry holds, or the time in seconds when the scenario has dt (it "
                    "holds from the first step at or after that time).")
    subsystem: Name = Field(description="The subsystem's name, as in couplings (integers are converted).")
    x: Optional[Components] = Field(
        None, description="Target states: n_i entries, null for a free one; or a map state name -> value (names "
                          "from the subsystem's 'states'). Omitted: every state free.")
    u: Optional[Components] = Field(
        None, description="Target inputs: m_i entries, null for a free one; or a map input name -> value. "
                          "Omitted: every input free.")
    y: Optional[Components] = Field(
        None, description="Target outputs (y_i = C x_i): p_i entries, null for a free one; or a map output name -> "
                          "value (names from the subsystem's 'outputs'). Omitted: every output free. Give x or y, "
                          "not both.")


class LinkFaultSpec(_Model):
    """Faults injected on one directed communication link."""

    source: Endpoint = Field(description="Sending side: a subsystem name or 'plant'.")
    target: Endpoint = Field(description="Receiving side: a subsystem name or 'plant'.")
    delay_ms: NonNegFloat = Field(0.0, description="Fixed delay on this link, milliseconds, >= 0.")
    jitter_ms: NonNegFloat = Field(0.0, description="Extra uniform random delay in [0, jitter_ms], milliseconds.")
    loss: Probability = Field(0.0, description="Probability in [0, 1) that a message on this link is dropped.")


class FaultsSpec(_Model):
    """Communication faults (seeded by ``seed``); per-link entries replace the global values on their link."""

    delay_ms: NonNegFloat = Field(0.0, description="Fixed delay on every link, milliseconds, >= 0.")
    jitter_ms: NonNegFloat = Field(0.0, description="Extra uniform random delay in [0, jitter_ms] on every link.")
    loss: Probability = Field(0.0, description="Probability in [0, 1) that any message is dropped.")
    links: list[LinkFaultSpec] = Field(default_factory=list, description="Per-link overrides of the above.")


class DiscretisationSpec(_Model):
    """How a continuous-time model (``time: continuous``) becomes the controllers' discrete model."""

    method: Literal["local-zoh", "exact-zoh"] = Field(
        "local-zoh", description="'local-zoh': each subsystem's exact zero-order hold with its neighbours' states and "
                                 "inputs held over the period (keeps the coupling graph); 'exact-zoh': the exact "
                                 "zero-order hold of the whole coupled system (entries outside the graph are refused "
                                 "above 'tolerance' unless 'truncate').")
    truncate: bool = Field(
        False, description="exact-zoh only: drop the entries that fall outside the coupling graph instead of refusing "
                           "them when they exceed the tolerance.")
    tolerance: NonNegFloat = Field(
        1e-9, description="exact-zoh only: the largest entry outside the coupling graph accepted, relative to the "
                          "largest entry of the discrete [A B]; larger ones are refused unless 'truncate'.")


class DisturbanceSpec(_Model):
    """An additive disturbance w(k) on the plant: x(k+1) = A x(k) + B u(k) + w(k)."""

    kind: Literal["uniform", "gaussian", "file", "step"] = Field(
        description="'uniform': w_i uniform in the box |w_i| <= bound_i; 'gaussian': normal with standard "
                    "deviations std_i; 'file': read from 'file'; 'step': constant from 'at' on, B d_u for the "
                    "input offsets d_u of 'input' plus the state offsets of 'state'.")
    bound: Optional[dict[Name, Vector]] = Field(
        None, description="uniform: half-widths per subsystem name (n_i entries >= 0); subsystems not listed get none.")
    std: Optional[dict[Name, Vector]] = Field(
        None, description="gaussian: standard deviations per subsystem name (n_i entries >= 0); subsystems not "
                          "listed get none.")
    file: Optional[str] = Field(
        None, description="file: a .npy or .csv file with one row per step and n columns (the global state order); "
                          "a relative path is read from the scenario file's folder.")
    at: Optional[Annotated[float, BeforeValidator(_setpoint_time)]] = Field(
        None, description="step: the step from which the disturbance acts (w(k) for k >= at is added to x(k+1)), "
                          "or the time in seconds when the scenario has dt (from the first step at or after it).")
    input: Optional[dict[Name, Vector]] = Field(
        None, description="step: offsets d_u of the inputs per subsystem name (m_i entries), entering as the "
                          "inputs do, through B_ii and the couplings' B_ij (the actuators off by d_u): w = B d_u; "
                          "subsystems not listed get none.")
    state: Optional[dict[Name, Vector]] = Field(
        None, description="step: offsets added to x_i(k+1) per subsystem name (n_i entries); subsystems not listed "
                          "get none. A step needs 'input', 'state' or both.")
    seed: Optional[Annotated[int, Field(strict=True, ge=0)]] = Field(
        None, description="Seed of the random draws (>= 0); null uses the scenario's seed.")

    @model_validator(mode="after")
    def _fields_of_kind(self) -> "DisturbanceSpec":
        needed = {"uniform": ("bound",), "gaussian": ("std",), "file": ("file",), "step": ("at", "input", "state")}
        either = ("input", "state")  # step: one of them or both (below)
        for kind, fields in needed.items():
            for field in fields:
                given = getattr(self, field) is not None
                if kind == self.kind and not given and field not in either:
                    raise SpecError(field, f"required when kind is '{kind}'")
                if kind != self.kind and given:
                    raise SpecError(field, f"only read when kind is '{kind}' (kind is '{self.kind}')")
        if self.kind == "step" and not (self.input or self.state):
            raise SpecError("input", "kind 'step' needs 'input' (offsets of the inputs, by subsystem name) or "
                                     "'state' (offsets of the states), or both")
        for field in ("bound", "std"):
            for name, vec in (getattr(self, field) or {}).items():
                for c, value in enumerate(vec):
                    if value < 0:
                        raise SpecError(f"{field}.{name}[{c}]", f"must be >= 0, got {value:g}")
        return self


FOURTANK_LEVELS = ("h1", "h2", "h3", "h4")
"""The state names plant.model: fourtank looks for (docs/fourtank.md)."""
FOURTANK_PUMPS = ("qa", "qb")
"""The input names plant.model: fourtank looks for."""


def _positive_entries(count: int):
    """A validator of a list of ``count`` numbers > 0."""
    def check(value: object) -> list[float]:
        vec = _vector(value, allow_inf=False)
        if len(vec) != count:
            raise SpecError("", f"expected {count} entries, got {len(vec)}")
        for i, v in enumerate(vec):
            if not v > 0:
                raise SpecError(f"[{i}]", f"expected a number > 0, got {v:g}")
        return vec
    return check


def _splits(value: object) -> list[float]:
    vec = _vector(value, allow_inf=False)
    if len(vec) != 2:
        raise SpecError("", f"expected 2 entries (gamma_a, gamma_b), got {len(vec)}")
    for i, v in enumerate(vec):
        if not 0 < v < 1:
            raise SpecError(f"[{i}]", f"a valve split must lie in (0, 1), got {v:g}")
    return vec


class FourTankSpec(_Model):
    """The quadruple-tank process that ``plant.model: fourtank`` simulates (defaults: the HD-MPC benchmark)."""

    area: PosFloat = Field(0.06, description="Cross-section S of each tank, m^2.")
    outlets: Annotated[list[float], BeforeValidator(_positive_entries(4))] = Field(
        default_factory=lambda: [1.31e-4, 1.51e-4, 9.27e-5, 8.82e-5],
        description="Outlet areas a1..a4 of the tanks, m^2 (4 entries > 0).")
    gamma: Annotated[list[float], BeforeValidator(_splits)] = Field(
        default_factory=lambda: [0.3, 0.4],
        description="Valve splits [gamma_a, gamma_b] in (0, 1): pump a sends gamma_a of its flow to tank 1 and the "
                    "rest to tank 4; pump b sends gamma_b to tank 2 and the rest to tank 3.")
    q0: Annotated[list[float], BeforeValidator(_positive_entries(2))] = Field(
        default_factory=lambda: [1.63, 2.0],
        description="The operating flows [qa, qb] in m^3/h (> 0): the states and inputs are deviations from them "
                    "and from their equilibrium levels.")
    g: PosFloat = Field(9.81, description="Gravity, m/s^2.")
    substeps: PosInt = Field(5, description="Runge-Kutta (RK4) steps per sampling period dt.")


def _per_subsystem_kind(value: object) -> object:
    """A disturbance model (``output`` or ``input``), or a map subsystem name -> one."""
    if isinstance(value, dict):
        return {_subsystem_name(key): _kind(v, f".{key}") for key, v in value.items()}
    return _kind(value, "")


def _kind(value: object, path: str) -> str:
    if value not in KINDS:
        raise SpecError(path, f"expected one of {', '.join(KINDS)}, got {_show(value)}")
    return str(value)


DisturbanceKinds = Annotated[Union[Literal["output", "input"], dict[str, Literal["output", "input"]]],
                             BeforeValidator(_per_subsystem_kind)]


def _positive_per_subsystem(value: object) -> object:
    """A number > 0, or a map subsystem name -> number > 0."""
    out = _per_subsystem(value)
    numbers: dict[str, float] = out if isinstance(out, dict) else {"": float(cast(float, out))}
    for key, number in numbers.items():
        if not number > 0:
            raise SpecError(f".{key}" if key else "", f"expected a number > 0, got {number:g}")
    return out


PositivePerSubsystem = Annotated[Union[float, dict[str, float]], BeforeValidator(_positive_per_subsystem)]


class NoiseSpec(_Model):
    """The noise weights of the agents' filters (dmpc.estimation.kalman.NoiseWeights): standard
    deviations as fractions of each quantity's scale, half the width of its bounds (1 where unbounded)."""

    state: PerSubsystem = Field(
        STATE_NOISE, description="The states' process noise per step, a fraction of each state's scale (>= 0); one "
                                 f"number, or a map subsystem name -> number (the others {STATE_NOISE:g}).")
    disturbance: PositivePerSubsystem = Field(
        DISTURBANCE_NOISE, description="The disturbances' random walk per step, a fraction of their scale (> 0): "
                                       "larger removes an offset faster; one number or a map by subsystem "
                                       f"(the others {DISTURBANCE_NOISE:g}).")
    measurement: PositivePerSubsystem = Field(
        MEASUREMENT_NOISE, description="The measurement noise, a fraction of each output's scale (> 0): larger "
                                       "trusts the model more and the sensors less; one number or a map by "
                                       f"subsystem (the others {MEASUREMENT_NOISE:g}).")


class EstimationSpec(_Model):
    """An observer per agent on the model with integrating disturbances (offset-free tracking)."""

    disturbance: DisturbanceKinds = Field(
        cast(Literal["output", "input"], DEFAULT_KIND), description="The disturbance model: 'output' (one constant bias per measured output) or "
                                  "'input' (one constant offset per own input); one for every subsystem, or a map "
                                  f"subsystem name -> kind (the others '{DEFAULT_KIND}').")
    noise: NoiseSpec = Field(default_factory=NoiseSpec, description="The filters' noise weights.")
    margin: Optional[PerSubsystemVector] = Field(
        None, description="Room the controllers keep for the estimation error, per state in the state's units "
                          "(>= 0): they keep the estimate x^ within the state bounds moved in by it, so the plant's "
                          "state stays within the bounds while |x - x^| <= margin (the verdict warns when it was "
                          "not). One number for every state, or a map subsystem name -> n_i entries (subsystems "
                          "not listed: none). Omitted: none.")


class MeasurementNoiseSpec(_Model):
    """Gaussian noise the plant adds to the outputs it reports, y = C x + v."""

    std: PerSubsystemVector = Field(
        description="Standard deviations (>= 0): one number for every output, or a map subsystem name -> p_i "
                    "entries (subsystems not listed: none).")
    seed: Optional[Annotated[int, Field(strict=True, ge=0)]] = Field(
        None, description="Seed of the draws (>= 0); null uses the scenario's seed.")


class PlantSpec(_Model):
    """What the plant simulates, when it is not the controllers' own model."""

    model: Literal["nominal", "exact", "fourtank"] = Field(
        "nominal", description="'nominal': the controllers' discrete model; 'exact': the exact zero-order hold of "
                               "the whole continuous-time system (time: continuous only), so that the controllers' "
                               "model error shows; 'fourtank': the nonlinear quadruple-tank process of 'fourtank', "
                               "integrated over each period dt (states named h1..h4, inputs qa, qb).")
    fourtank: Optional[FourTankSpec] = Field(
        None, description="model: fourtank only: the tanks' parameters; omitted: the HD-MPC benchmark's.")
    disturbance: Optional[DisturbanceSpec] = Field(
        None, description="An additive disturbance w(k) on every state update; null for none.")
    measurement_noise: Optional[MeasurementNoiseSpec] = Field(
        None, description="Noise on the outputs the plant reports to the agents; null for none.")

    @model_validator(mode="after")
    def _fourtank_only(self) -> "PlantSpec":
        if self.fourtank is not None and self.model != "fourtank":
            raise SpecError("fourtank", f"only read when model is 'fourtank' (model is '{self.model}'): remove it "
                                        "(--set plant.fourtank=null)")
        return self


class Scenario(_Model):
    """A complete experiment: the coupled system, the design choices and the run options."""

    name: str = Field(description="Short name of the scenario (used in run folders and reports).")
    description: str = Field("", description="Free text describing the scenario.")
    subsystems: Optional[Annotated[list[SubsystemSpec], Field(min_length=1)]] = Field(
        None, description="The subsystems, in order (0-based index = position). Give this or 'family'.")
    family: Optional[ChainFamily] = Field(
        None, description="A generated family of identical subsystems instead of 'subsystems'.")
    couplings: list[CouplingSpec] = Field(
        default_factory=list, description="Dynamic couplings A_ij/B_ij (each also a communication edge); "
                                          "with a family they are added to the chain's.")
    graph: list[tuple[Name, Name]] = Field(
        default_factory=list, description="Extra undirected communication edges [a, b] without dynamic coupling.")
    horizon: AutoPosInt = Field(
        "auto", description="Prediction horizon N >= 1, or 'auto': the smallest N for which the distributed k = 0 "
                            "step finds a plan for every agent, plus max(2, ceil(0.2 N)) steps (searched up to 200).")
    steps: PosInt = Field(30, description="Number of closed-loop steps to simulate, >= 1.")
    seed: Annotated[int, Field(strict=True, ge=0)] = Field(
        0, description="Seed (>= 0) of every random choice (fault injection).")
    design: DesignSpec = Field(default_factory=DesignSpec, description="Offline gain design.")
    terminal: TerminalSpec = Field(default_factory=TerminalSpec, description="Initial terminal box.")
    options: OptionsSpec = Field(default_factory=OptionsSpec, description="Algorithm and runtime options.")
    faults: FaultsSpec = Field(default_factory=FaultsSpec, description="Injected communication faults.")
    dt: Optional[PosFloat] = Field(
        None, description="Sampling period of the model in seconds: results and figures use seconds, and a "
                          "continuous-time model is discretised with it. Not the realtime period (options.dt).")
    time: Literal["discrete", "continuous"] = Field(
        "discrete", description="'discrete': A, B, A_ij, B_ij are the discrete-time model; 'continuous': they are "
                                "continuous-time, discretised with dt by 'discretisation'.")
    discretisation: DiscretisationSpec = Field(
        default_factory=DiscretisationSpec, description="How a continuous-time model is discretised.")
    plant: PlantSpec = Field(default_factory=PlantSpec, description="The simulated plant: its model and disturbance.")
    setpoints: list[SetpointSpec] = Field(
        default_factory=list, description="The setpoint schedule, piecewise constant: the latest entry of each "
                                          "subsystem at or before a step holds; a subsystem without one keeps the "
                                          "origin as its target.")
    estimation: Optional[EstimationSpec] = Field(
        None, description="An observer per agent that estimates the states and constant disturbances from the "
                          "measured outputs ({} for the defaults); null: the plant reports the whole state.")

    def resolved_subsystems(self) -> list[SubsystemSpec]:
        """The subsystems in order, with a family expanded."""
        if self.family is not None:
            return self.family.members()
        assert self.subsystems is not None, "a scenario has 'subsystems' or 'family' (_cross_checks)"
        return list(self.subsystems)

    def resolved_couplings(self) -> list[CouplingSpec]:
        """The family's chain couplings (if any) followed by the explicit ones."""
        generated = [] if self.family is None else self.family.couplings()
        return generated + list(self.couplings)

    def subsystem_path(self, index: int) -> str:
        """Where subsystem ``index`` is written in the file (for error messages)."""
        return "family.subsystem" if self.family is not None else f"subsystems[{index}]"

    @model_validator(mode="before")
    @classmethod
    def _one_source(cls, data: object) -> object:
        if isinstance(data, dict) and data.get("subsystems") is not None and data.get("family") is not None:
            raise SpecError("family", "give either 'subsystems' or 'family', not both")
        return data

    @model_validator(mode="after")
    def _cross_checks(self) -> "Scenario":
        if self.subsystems is None and self.family is None:
            raise SpecError("subsystems", "required (or give 'family' to generate the subsystems)")
        subs = self.resolved_subsystems()
        index: dict[str, int] = {}
        for i, s in enumerate(subs):
            if s.name in index:
                raise SpecError(f"subsystems[{i}].name",
                                f"duplicate subsystem name '{s.name}' (also subsystems[{index[s.name]}])")
            index[s.name] = i
        _check_couplings(self, subs, index)
        _check_graph(self.graph, index)
        _check_gains(self, subs)
        _check_alpha0(self.terminal.alpha0, subs, index)
        _check_revision_bounds(self, subs, index)
        _check_links(self.faults.links, index)
        _check_loss(self)
        _check_time(self)
        _check_disturbance(self.plant.disturbance, subs, index)
        _check_measurements_need_estimation(self, subs)
        _check_estimation(self.estimation, index, subs, self)
        _check_measurement_noise(self.plant.measurement_noise, subs, index)
        _check_setpoints(self, subs, index)
        _check_trigger(self, index)
        return self


def _known(index: dict[str, int]) -> str:
    names = list(index)
    shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
    return f"known: {shown}"


def _check_name(name: str, index: dict[str, int], path: str) -> None:
    if name not in index:
        raise SpecError(path, f"unknown subsystem '{name}' ({_known(index)})")


def _check_couplings(scn: Scenario, subs: list[SubsystemSpec], index: dict[str, int]) -> None:
    seen = {(c.target, c.source) for c in (scn.family.couplings() if scn.family else [])}
    for k, c in enumerate(scn.couplings):
        path = f"couplings[{k}]"
        _check_name(c.target, index, f"{path}.target")
        _check_name(c.source, index, f"{path}.source")
        if c.target == c.source:
            raise SpecError(f"{path}.source", f"must differ from target ('{c.target}'): "
                                              "a subsystem's own dynamics are its A and B")
        if (c.target, c.source) in seen:
            raise SpecError(path, f"duplicate coupling of '{c.target}' by '{c.source}'")
        seen.add((c.target, c.source))
        t, s = subs[index[c.target]], subs[index[c.source]]
        check_shape(c.A, (t.n, s.n), f"{path}.A", f"n_target x n_source = {t.n} x {s.n}")
        if c.B is not None:
            check_shape(c.B, (t.n, s.m), f"{path}.B", f"n_target x m_source = {t.n} x {s.m}")


def _check_graph(graph: list[tuple[str, str]], index: dict[str, int]) -> None:
    for k, (a, b) in enumerate(graph):
        _check_name(a, index, f"graph[{k}][0]")
        _check_name(b, index, f"graph[{k}][1]")
        if a == b:
            raise SpecError(f"graph[{k}]", f"an edge needs two different subsystems, got '{a}' twice")


def _check_gains(scn: Scenario, subs: list[SubsystemSpec]) -> None:
    if scn.design.gains != "given":
        return
    for i, s in enumerate(subs):
        for field in ("K", "P"):
            if getattr(s, field) is None:
                raise SpecError(f"{scn.subsystem_path(i)}.{field}", "required when design.gains is 'given'")


def _check_alpha0(alpha0: dict[str, list[float]] | None, subs: list[SubsystemSpec], index: dict[str, int]) -> None:
    for name, vec in (alpha0 or {}).items():
        _check_name(name, index, f"terminal.alpha0.{name}")
        n = subs[index[name]].n
        check_length(vec, n, f"terminal.alpha0.{name}", f"n = {n} states of subsystem '{name}'")


def _check_revision_bounds(scn: Scenario, subs: list[SubsystemSpec], index: dict[str, int]) -> None:
    if scn.options.tube != "robust":
        return
    for c in scn.resolved_couplings():
        i = index[c.source]
        if subs[i].revision_bound is None:
            raise SpecError(f"{scn.subsystem_path(i)}.revision_bound",
                            f"required when options.tube is 'robust' (subsystem '{c.source}' is a coupling "
                            f"source of '{c.target}')")


def _check_links(links: list[LinkFaultSpec], index: dict[str, int]) -> None:
    for k, link in enumerate(links):
        for field in ("source", "target"):
            name = getattr(link, field)
            if name != PLANT and name not in index:
                raise SpecError(f"faults.links[{k}].{field}",
                                f"unknown endpoint '{name}' (a subsystem name or '{PLANT}'; {_known(index)})")
        if link.source == link.target:
            raise SpecError(f"faults.links[{k}].target", f"must differ from source ('{link.source}')")


def _check_loss(scn: Scenario) -> None:
    """Lost messages need a deadline: in lockstep without one the run would wait for them forever."""
    if scn.options.deadline is not None or scn.options.mode == "realtime":
        return
    lossy = ["faults.loss"] if scn.faults.loss > 0 else []
    lossy += [f"faults.links[{k}].loss" for k, link in enumerate(scn.faults.links) if link.loss > 0]
    if lossy:
        raise SpecError(lossy[0], "lost messages need a deadline in lockstep mode, or the run would wait for them "
                                  "forever: set options.deadline (--deadline S) or options.mode: realtime")


def _check_time(scn: Scenario) -> None:
    if scn.time == "continuous" and scn.dt is None:
        raise SpecError("dt", "required when time is 'continuous' (the sampling period used to discretise)")
    if scn.plant.model == "exact" and scn.time != "continuous":
        raise SpecError("plant.model", "'exact' needs time: continuous (a discrete-time model is already exact)")
    if scn.plant.model == "fourtank":
        _check_fourtank(scn)


def fourtank_positions(scn: Scenario) -> tuple[list[int], list[int]]:
    """Where h1..h4 sit in the global state and qa, qb in the global input of the scenario ``scn``
    (plant.model: fourtank).

    Raises
    ------
    SpecError
        A level or pump the subsystems do not name, or a name given twice.
    """
    states: dict[str, int] = {}
    inputs: dict[str, int] = {}
    x_at = u_at = 0
    for i, sub in enumerate(scn.resolved_subsystems()):
        for kind, labels, found, at, wanted in (("states", sub.states, states, x_at, FOURTANK_LEVELS),
                                                ("inputs", sub.inputs, inputs, u_at, FOURTANK_PUMPS)):
            for offset, label in enumerate(labels or []):
                if label.name in wanted and label.name in found:
                    raise SpecError(f"{scn.subsystem_path(i)}.{kind}[{offset}].name",
                                    f"'{label.name}' is named twice: plant.model 'fourtank' needs each level and "
                                    "pump once")
                found[label.name] = at + offset
        x_at, u_at = x_at + sub.n, u_at + sub.m
    missing = [name for name in FOURTANK_LEVELS if name not in states]
    missing += [name for name in FOURTANK_PUMPS if name not in inputs]
    if missing:
        raise SpecError("plant.model", f"'fourtank' needs the subsystems to name their states "
                                       f"{', '.join(FOURTANK_LEVELS)} and their inputs {', '.join(FOURTANK_PUMPS)} "
                                       f"(states: and inputs: of each subsystem); missing: {', '.join(missing)}")
    return [states[name] for name in FOURTANK_LEVELS], [inputs[name] for name in FOURTANK_PUMPS]


def _check_fourtank(scn: Scenario) -> None:
    if scn.dt is None:
        raise SpecError("dt", "required when plant.model is 'fourtank' (the period the tanks are integrated over)")
    fourtank_positions(scn)
    subs = scn.resolved_subsystems()
    given = [s.operating_point is not None for s in subs]
    if any(given):
        if not all(given):
            i = given.index(False)
            raise SpecError(f"{scn.subsystem_path(i)}.operating_point", "required: another subsystem gives one, and "
                                                                       "the tanks are then given levels and flows in "
                                                                       "m and m^3/h, not deviations")
        if scn.plant.fourtank is not None and "q0" in scn.plant.fourtank.model_fields_set:
            raise SpecError("plant.fourtank.q0", "not read when the subsystems give operating_point (the levels and "
                                                 "flows are then the plant's own): remove it")


def _check_disturbance(spec: DisturbanceSpec | None, subs: list[SubsystemSpec], index: dict[str, int]) -> None:
    if spec is None:
        return
    for field in ("bound", "std", "state", "input"):
        for name, vec in (getattr(spec, field) or {}).items():
            path = f"plant.disturbance.{field}.{name}"
            _check_name(name, index, path)
            sub = subs[index[name]]
            if field == "input":
                check_length(vec, sub.m, path, f"m = {sub.m} inputs of subsystem '{name}'")
            else:
                check_length(vec, sub.n, path, f"n = {sub.n} states of subsystem '{name}'")


def setpoint_values(spec: SetpointSpec, sub: SubsystemTemplate, kind: str, path: str) -> list[float | None]:
    """The components of ``spec.x`` (``kind`` 'x'), ``spec.u`` ('u') or ``spec.y`` ('y') in order, None
    where free.

    Parameters
    ----------
    spec : SetpointSpec
        The setpoint entry, its ``x``, ``u`` or ``y`` given as a list, a map of the subsystem's state,
        input or output names, or not at all (every component free).
    sub : SubsystemTemplate
        The subsystem ``spec`` names: its n_i, m_i, p_i and the labels of its states, inputs and outputs.
    kind : {"x", "u", "y"}
        Which of the three to read.
    path : str
        Where ``spec`` is written (e.g. ``"setpoints[0]"``), for the SpecError of a list of the
        wrong length or an unknown name.

    Returns
    -------
    list of float or None
        n_i entries for ``"x"``, m_i for ``"u"``, p_i for ``"y"``.
    """
    given = {"x": spec.x, "u": spec.u, "y": spec.y}[kind]
    size = {"x": sub.n, "u": sub.m, "y": sub.p}[kind]
    if given is None:
        return [None] * size
    noun = {"x": "state", "u": "input", "y": "output"}[kind]
    if isinstance(given, list):
        what = {"x": "n_i", "u": "m_i", "y": "p_i"}[kind]
        if len(given) != size:
            raise SpecError(f"{path}.{kind}", f"expected {size} entries ({what} = {size} {noun}s of subsystem "
                                              f"'{spec.subsystem}'), got {len(given)}")
        return list(given)
    labels = sub.output_labels() if kind == "y" else (sub.states if kind == "x" else sub.inputs)
    if not labels:
        raise SpecError(f"{path}.{kind}", f"names need the subsystem's '{noun}s' "
                                          f"(subsystem '{spec.subsystem}' names none): give a list instead")
    names = [label.name for label in labels]
    for key in given:
        if key not in names:
            raise SpecError(f"{path}.{kind}.{key}", f"subsystem '{spec.subsystem}' has no {noun} '{key}' "
                                                    f"(it has {', '.join(names)})")
    return [given.get(name) for name in names]


def _component_path(spec: SetpointSpec, kind: str, names: list[str], c: int) -> str:
    """Where component ``c`` of ``spec.<kind>`` is written: ``.x.h1`` for a map, ``.x[0]`` for a list."""
    given = {"x": spec.x, "u": spec.u, "y": spec.y}[kind]
    return f".{kind}.{names[c]}" if isinstance(given, dict) else f".{kind}[{c}]"


def _check_setpoints(scn: Scenario, subs: list[SubsystemSpec], index: dict[str, int]) -> None:
    if scn.setpoints and (error := lacks(scn.options.method, "tracks_setpoints")) is not None:
        raise SpecError("setpoints", f"{error}: set options.method to one of them")
    if scn.setpoints and scn.options.tube == "robust":
        raise SpecError("setpoints", "setpoints are not tracked with options.tube: robust (the reference "
                                     "governor's test of a target does not include the tube's tightening)")
    for e, spec in enumerate(scn.setpoints):
        path = f"setpoints[{e}]"
        _check_name(spec.subsystem, index, f"{path}.subsystem")
        if scn.dt is None and spec.at != int(spec.at):
            raise SpecError(f"{path}.at", f"expected a whole step, got {spec.at:g} (the scenario has no dt, so 'at' "
                                          "counts steps)")
        if spec.x is not None and spec.y is not None:
            raise SpecError(f"{path}.y", "give either x (states) or y (outputs), not both")
        sub = subs[index[spec.subsystem]]
        subpath = scn.subsystem_path(index[spec.subsystem])
        for kind, set_spec, set_path in (("x", sub.state, "state"), ("u", sub.input, "input")):
            values = setpoint_values(spec, sub, kind, path)
            if not isinstance(set_spec, BoxSpec):
                continue
            for c, value in enumerate(values):
                if value is not None and not set_spec.lower[c] <= value <= set_spec.upper[c]:
                    where = f"{path}.{kind}[{c}]"
                    name = (sub.states if kind == "x" else sub.inputs)
                    label = f" ({name[c].label})" if name else ""
                    raise SpecError(where, f"the target {value:g}{label} of subsystem '{spec.subsystem}' is outside "
                                           f"{'X_i' if kind == 'x' else 'U_i'} [{set_spec.lower[c]:g}, "
                                           f"{set_spec.upper[c]:g}] ({subpath}.{set_path})")
        _check_output_setpoint(spec, sub, path, subpath)
        if scn.estimation is not None:
            _check_measured(spec, sub, path, subpath)


def _check_output_setpoint(spec: SetpointSpec, sub: SubsystemTemplate, path: str, subpath: str) -> None:
    """The requested outputs that are a state alone (a row e_j of C) within that state's box."""
    values = setpoint_values(spec, sub, "y", path)
    if spec.y is None or not isinstance(sub.state, BoxSpec):
        return
    outputs = sub.output_labels()
    for r, j in sub.state_rows().items():
        value = values[r]
        lo, hi = sub.state.lower[j], sub.state.upper[j]
        if value is not None and not lo <= value <= hi:
            state = sub.states[j].label if sub.states else f"x{j + 1}"
            raise SpecError(path + _component_path(spec, "y", [o.name for o in outputs], r),
                            f"the target {value:g} of output {outputs[r].label} of subsystem '{spec.subsystem}' is "
                            f"outside X_i [{lo:g}, {hi:g}] (it measures the state {state}; {subpath}.state)")


def _check_measured(spec: SetpointSpec, sub: SubsystemTemplate, path: str, subpath: str) -> None:
    """With estimation, a requested state must be an output on its own (a row e_j of C): it is then
    tracked as that output; any other state request is refused."""
    if spec.x is None:
        return
    measured = set(sub.state_rows().values())
    names = [label.name for label in sub.states] if sub.states else [f"x{j + 1}" for j in range(sub.n)]
    for j, value in enumerate(setpoint_values(spec, sub, "x", path)):
        if value is not None and j not in measured:
            outputs = ", ".join(label.name for label in sub.output_labels())
            raise SpecError(path + _component_path(spec, "x", names, j),
                            f"with estimation, setpoints name measured outputs (y) or inputs (u): state {names[j]} "
                            f"of subsystem '{spec.subsystem}' is not measured on its own (no row of {subpath}.C picks "
                            f"it alone), so its steady state depends on the disturbance estimate; request an output "
                            f"instead (y: {{name: value}}, outputs {outputs}), or measure {names[j]} (a row of "
                            f"{subpath}.C)")


def _check_measurements_need_estimation(scn: Scenario, subs: list[SubsystemSpec]) -> None:
    if scn.estimation is not None:
        return
    for i, sub in enumerate(subs):
        if not sub.measures_state:
            raise SpecError(f"{scn.subsystem_path(i)}.C", "measures only some of the states (C is not the identity), "
                                                          "so the agents need an observer for the others: add "
                                                          "'estimation' (estimation: {} for the defaults), or omit C to "
                                                          "measure every state")


def _check_estimation(spec: EstimationSpec | None, index: dict[str, int], subs: list[SubsystemSpec],
                      scn: Scenario) -> None:
    if spec is None:
        return
    maps = [("estimation.disturbance", spec.disturbance)]
    maps += [(f"estimation.noise.{field}", getattr(spec.noise, field)) for field in NoiseSpec.model_fields]
    for where, value in maps:
        for name in (value if isinstance(value, dict) else {}):
            _check_name(name, index, f"{where}.{name}")
    margin = spec.margin
    if isinstance(margin, dict):
        for name, vec in margin.items():
            _check_name(name, index, f"estimation.margin.{name}")
            n = subs[index[name]].n
            check_length(vec, n, f"estimation.margin.{name}", f"n = {n} states of subsystem '{name}'")
    for i, sub in enumerate(subs):
        values = state_margin(margin, sub)
        if values is None or not any(values):
            continue
        if sub.state is None:
            raise SpecError(f"estimation.margin.{sub.name}", f"subsystem '{sub.name}' has no state bounds to keep a "
                                                             "margin from: remove its margin")
        at = list(sub.operating_point.x) if sub.operating_point is not None else [0.0] * sub.n
        try:
            _margin_set(sub.state, values).origin_inside(
                f"{scn.subsystem_path(i)}.state", at,
                "the operating point" if sub.operating_point is not None else "the origin")
        except SpecError as exc:
            raise SpecError(f"estimation.margin.{sub.name}", f"too large: the state bounds moved in by it leave no room "
                                                             f"around the target ({exc.path}: {exc.message})") from None


def state_margin(margin: float | dict[str, list[float]] | None, sub: SubsystemTemplate | SubsystemSpec) -> list[float] | None:
    """The estimation margin of the subsystem ``sub`` (n_i values), from ``estimation.margin``: None without one."""
    if margin is None:
        return None
    if isinstance(margin, dict):
        name = getattr(sub, "name", None)
        return list(margin[name]) if name in margin else None
    return [float(margin)] * sub.n


def _margin_set(spec: BoxSpec | PolytopeSpec, margin: list[float]) -> BoxSpec | PolytopeSpec:
    """``spec`` moved in by the box ``margin``: each bound of a box by its state's margin, each row h_r of a
    polytope by sum_j |H_rj| margin_j."""
    if isinstance(spec, BoxSpec):
        return BoxSpec.model_construct(lower=[lo + e for lo, e in zip(spec.lower, margin)],
                                       upper=[hi - e for hi, e in zip(spec.upper, margin)])
    return PolytopeSpec.model_construct(H=spec.H, h=[h - sum(abs(a) * e for a, e in zip(row, margin))
                                                     for row, h in zip(spec.H, spec.h)])


def _check_measurement_noise(spec: MeasurementNoiseSpec | None, subs: list[SubsystemSpec],
                             index: dict[str, int]) -> None:
    if spec is None or not isinstance(spec.std, dict):
        return
    for name, vec in spec.std.items():
        path = f"plant.measurement_noise.std.{name}"
        _check_name(name, index, path)
        p = subs[index[name]].p
        check_length(vec, p, path, f"p = {p} outputs of subsystem '{name}'")


def _check_trigger(scn: Scenario, index: dict[str, int]) -> None:
    opts = scn.options
    for field in ("trigger_threshold", "trigger_cost"):
        for name in (getattr(opts, field) if isinstance(getattr(opts, field), dict) else {}):
            _check_name(name, index, f"options.{field}.{name}")
    if opts.trigger != "event":
        return
    if (error := lacks(opts.method, "supports_trigger")) is not None:
        raise SpecError("options.trigger", f"'event': {error}: set options.method to one of them, or "
                                           "options.trigger to 'always'")
    if opts.iterations != 1:
        raise SpecError("options.trigger", f"'event' needs one Jacobi round per step (options.iterations is "
                                           f"{opts.iterations}): an agent keeps or solves once per step")


def per_subsystem(value: float | dict[str, float], names: list[str], default: float) -> tuple[float, ...]:
    """A PerSubsystem option as one number per subsystem, in order (``default`` where a map leaves one out).

    Parameters
    ----------
    value : float or dict of str to float
        The option as the file gives it: one number for every subsystem, or a map subsystem name ->
        number.
    names : list of str
        The subsystems' names, in the scenario's order.
    default : float
        The number of a subsystem the map leaves out.
    """
    if isinstance(value, dict):
        return tuple(float(value.get(name, default)) for name in names)
    return tuple(float(value) for _ in names)
