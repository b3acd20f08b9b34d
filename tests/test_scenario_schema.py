"""Scenario files: the shipped scenarios, families, overrides, dump round trip and building the system."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import get_args

import jsonschema
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel
from scipy.linalg import block_diag

from dmpc.core.system import CoupledSystem
from dmpc.scenario import (
    Scenario,
    ScenarioError,
    alpha0_vector,
    build_system,
    dump_resolved,
    given_gains,
    load_scenario,
    parse_override,
    scenario_json_schema,
    validate_scenario,
)

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = sorted((ROOT / "scenarios").glob("*.yaml"))
PAPER = ROOT / "scenarios" / "paper.yaml"
CHAIN = ROOT / "scenarios" / "chain.yaml"


def _small(**extra) -> dict:
    """A valid two-subsystem scenario mapping."""
    sub = {"A": [[1.0, 0.5], [0.0, 1.0]], "B": [[0.0], [1.0]], "Q": [[1.0, 0.0], [0.0, 1.0]], "R": [[0.1]],
           "input": {"lower": [-1.0], "upper": [1.0]}}
    data = {"name": "small",
            "subsystems": [{"name": "a", **sub, "x0": [1.0, 0.0]}, {"name": "b", **sub, "x0": [0.0, 1.0]}],
            "couplings": [{"target": "a", "source": "b", "A": [[0.1, 0.0], [0.0, 0.1]]}]}
    data.update(extra)
    return data


def _models(root: type[BaseModel]) -> set[type[BaseModel]]:
    """All pydantic models reachable from ``root`` through field annotations."""
    def types_in(tp):
        yield tp
        for arg in get_args(tp):
            yield from types_in(arg)

    seen: set[type[BaseModel]] = set()
    todo = [root]
    while todo:
        model = todo.pop()
        if model not in seen:
            seen.add(model)
            for field in model.model_fields.values():
                todo += [t for t in types_in(field.annotation) if isinstance(t, type) and issubclass(t, BaseModel)]
    return seen


# --- shipped scenarios ---------------------------------------------------------------------------

@pytest.mark.parametrize("path", SCENARIOS, ids=[p.name for p in SCENARIOS])
def test_shipped_scenarios_load_and_build(path):
    scn = load_scenario(path)
    system = build_system(scn)
    assert isinstance(system, CoupledSystem)
    assert system.A.shape == (system.n, system.n)
    assert system.B.shape == (system.n, system.m)
    assert np.array_equal(alpha0_vector(scn, system), np.zeros(system.n))


def test_shipped_scenarios_exist():
    assert {p.name for p in SCENARIOS} >= {"paper.yaml", "paper-lmi.yaml", "chain.yaml"}


def test_paper_is_algorithm_md_section_5():
    scn = load_scenario(PAPER)
    system = build_system(scn)
    assert scn.design.gains == "given" and scn.horizon == 10 and scn.steps == 30
    assert scn.terminal.beta0 == 0.5 and scn.terminal.alpha0 is None
    assert [s.name for s in system.subsystems] == ["1", "2", "3", "4"]
    assert system.edges == ((0, 1), (1, 2), (2, 3))
    for s in system.subsystems:
        assert np.array_equal(s.A, [[1.1, 1.0], [0.0, 1.3]])
        assert np.array_equal(s.B, [[1.0], [1.0]])
        assert np.array_equal(s.Q, np.eye(2)) and np.array_equal(s.R, [[0.01]])
        assert np.array_equal(s.input_set.lower, [-2.5]) and np.array_equal(s.input_set.upper, [2.5])
        assert s.state_set is None
    assert len(system.couplings) == 6
    for c in system.couplings:
        assert abs(c.target - c.source) == 1
        assert np.array_equal(c.A, [[0.0, 0.1], [0.2, 0.2]]) and not np.any(c.B)
    assert np.allclose(system.x0, [2.794, 2.5, 2.08, 2.2, 2.194, -2.305, -2.8, 2.5])
    K, P = given_gains(scn)
    assert np.array_equal(K[1], [[-0.7452, -1.113]])
    assert np.array_equal(P[2], P[3]) and np.array_equal(K[2], K[3])
    # The printed gains (docs/algorithm.md, "The paper's example, corrected"): rho(A+BK) = 0.697 and (10) margin -0.350.
    Kg, Pg = block_diag(*K), block_diag(*P)
    AK = system.A + system.B @ Kg
    assert max(abs(np.linalg.eigvals(AK))) == pytest.approx(0.697, abs=1e-3)
    lhs = AK.T @ Pg @ AK - Pg + system.Q + Kg.T @ system.R @ Kg
    assert np.linalg.eigvalsh(lhs).max() == pytest.approx(-0.350, abs=1e-3)


def test_paper_lmi_is_the_paper_without_gains():
    paper, lmi = load_scenario(PAPER), load_scenario(ROOT / "scenarios" / "paper-lmi.yaml")
    assert lmi.design.gains == "lmi"
    assert all(s.K is None and s.P is None for s in lmi.resolved_subsystems())
    a, b = build_system(paper), build_system(lmi)
    assert np.array_equal(a.A, b.A) and np.array_equal(a.B, b.B) and np.array_equal(a.x0, b.x0)
    assert a.edges == b.edges
    with pytest.raises(ScenarioError, match=r"design\.gains"):
        given_gains(lmi)


def test_chain_default():
    scn = load_scenario(CHAIN)
    assert scn.family is not None and scn.family.M == 8 and scn.design.gains == "lmi"
    system = build_system(scn)
    assert system.M == 8 and system.A.shape == (16, 16)


@pytest.mark.parametrize("M", range(1, 13))
def test_chain_family_sizes(M):
    scn = load_scenario(CHAIN, {"family.M": M})
    system = build_system(scn)
    assert system.M == M
    assert [s.name for s in system.subsystems] == [str(i) for i in range(1, M + 1)]
    assert system.edges == tuple((i, i + 1) for i in range(M - 1))
    assert len(system.couplings) == 2 * (M - 1)
    cycle = scn.family.x0_cycle
    for i, s in enumerate(system.subsystems):
        assert np.array_equal(s.x0, cycle[i % len(cycle)])
    for c in system.couplings:
        assert np.array_equal(c.A, [[0.0, 0.1], [0.2, 0.2]])
    assert system.A.shape == (2 * M, 2 * M)


def test_chain_overrides_via_parse_override():
    overrides = dict(parse_override(t) for t in ["family.M=3", "horizon=5", "options.iterations=3",
                                                  "design.gains=lqr", "options.mode=realtime"])
    scn = load_scenario(CHAIN, overrides)
    assert (scn.family.M, scn.horizon, scn.options.iterations) == (3, 5, 3)
    assert scn.design.gains == "lqr" and scn.options.mode == "realtime"


# --- dump / schema / docs ------------------------------------------------------------------------

@pytest.mark.parametrize("path", SCENARIOS, ids=[p.name for p in SCENARIOS])
def test_dump_resolved_round_trips(path, tmp_path):
    scn = load_scenario(path)
    text = dump_resolved(scn)
    out = tmp_path / "resolved.yaml"
    out.write_text(text)
    again = load_scenario(out)
    assert again == scn
    assert dump_resolved(again) == text
    assert "initial_iterations" in text and "deadline" in text  # defaults are written out


def test_dump_resolved_round_trips_rich_scenario(tmp_path):
    data = _small(
        graph=[["a", "b"]],
        terminal={"alpha0": {"a": [0.1, -0.1]}, "beta0": 0.25},
        options={"tube": "robust", "deadline": 0.05, "mode": "realtime"},
        faults={"delay_ms": 2, "links": [{"source": "plant", "target": "a", "loss": 0.1}]},
    )
    data["subsystems"][0]["state"] = {"lower": [-float("inf"), -5.0], "upper": [float("inf"), 5.0]}
    data["subsystems"][1]["input"] = {"H": [[1.0], [-1.0]], "h": [1.0, 2.0]}
    data["subsystems"][1]["revision_bound"] = {"state": [0.1, 0.1], "input": [0.05]}
    scn = validate_scenario(data)
    out = tmp_path / "rich.yaml"
    out.write_text(dump_resolved(scn))
    assert load_scenario(out) == scn


def test_every_field_has_a_description():
    models = _models(Scenario)
    assert len(models) >= 12
    for model in models:
        assert model.model_config.get("extra") == "forbid", model
        for name, field in model.model_fields.items():
            assert field.description, f"{model.__name__}.{name} has no description"


def test_json_schema_describes_and_validates_shipped_files():
    schema = scenario_json_schema()
    assert schema["additionalProperties"] is False
    assert set(schema["properties"]) >= {"name", "subsystems", "family", "couplings", "graph", "horizon",
                                         "steps", "seed", "design", "terminal", "options", "faults"}
    for path in SCENARIOS:
        jsonschema.validate(yaml.safe_load(path.read_text()), schema)


def test_docs_document_every_field():
    docs = (ROOT / "docs" / "scenarios.md").read_text()
    for model in _models(Scenario):
        for name in model.model_fields:
            assert f"`{name}`" in docs, f"docs/scenarios.md does not mention `{name}` ({model.__name__})"


# --- building ------------------------------------------------------------------------------------

def test_names_ints_become_strings_and_graph_edges():
    data = _small(graph=[["a", "b"]])
    data["subsystems"][0]["name"] = 10
    data["couplings"] = []
    data["graph"] = [[10, "b"]]
    scn = validate_scenario(data)
    system = build_system(scn)
    assert system.subsystems[0].name == "10"
    assert system.edges == ((0, 1),) and system.couplings == ()


def test_coupling_b_defaults_to_zeros_and_sets():
    data = _small()
    data["subsystems"][1]["input"] = {"H": [[1.0], [-1.0]], "h": [1.0, 2.0]}
    data["subsystems"][0]["state"] = {"lower": [-float("inf"), -5.0], "upper": [float("inf"), 5.0]}
    system = build_system(validate_scenario(data))
    (c,) = system.couplings
    assert (c.target, c.source) == (0, 1) and c.B.shape == (2, 1) and not np.any(c.B)
    u1 = system.subsystems[1].input_set
    assert not u1.is_box and np.array_equal(u1.upper, [1.0, 2.0]) and np.all(np.isneginf(u1.lower))
    x0 = system.subsystems[0].state_set
    assert x0.is_box and x0.upper[0] == np.inf and x0.lower[1] == -5.0
    assert system.subsystems[1].state_set is None


def test_alpha0_vector_and_given_gains():
    data = _small(terminal={"alpha0": {"b": [0.1, 0.2]}}, design={"gains": "given"})
    for sub in data["subsystems"]:
        sub["K"] = [[-0.1, -0.2]]
        sub["P"] = [[2.0, 0.1], [0.1, 1.0]]
    scn = validate_scenario(data)
    system = build_system(scn)
    assert np.array_equal(alpha0_vector(scn, system), [0.0, 0.0, 0.1, 0.2])
    K, P = given_gains(scn)
    assert [k.shape for k in K] == [(1, 2), (1, 2)] and np.array_equal(P[1], P[1].T)


def test_gains_not_needed_unless_given():
    data = _small()
    data["subsystems"][0]["K"] = [[-0.1, -0.2]]  # allowed and ignored with gains: lmi
    assert validate_scenario(data).design.gains == "lmi"


def test_family_with_extra_couplings_and_graph():
    scn = load_scenario(CHAIN, {"family.M": 4, "graph": [[1, 4]],
                                "couplings": [{"target": 1, "source": 3, "A": [[0.0, 0.0], [0.0, 0.01]]}]})
    system = build_system(scn)
    assert system.edges == ((0, 1), (0, 2), (0, 3), (1, 2), (2, 3))
    assert len(scn.resolved_couplings()) == 7


def test_validate_scenario_does_not_modify_input():
    data = _small()
    before = copy.deepcopy(data)
    validate_scenario(data, {"horizon": 3, "options.iterations": 2})
    assert data == before


def test_overrides_create_missing_sections_and_index_lists():
    scn = load_scenario(PAPER, {"options.iterations": 4, "subsystems[1].x0": [0.5, 0.5],
                                "subsystems.2.x0": [0.1, 0.2], "terminal.alpha0.1": [0.01, 0.0]})
    assert scn.options.iterations == 4
    assert scn.subsystems[1].x0 == [0.5, 0.5] and scn.subsystems[2].x0 == [0.1, 0.2]
    assert scn.terminal.alpha0 == {"1": [0.01, 0.0]}


@pytest.mark.parametrize("text, expected", [
    ("family.M=8", ("family.M", 8)),
    ("options.mode = realtime", ("options.mode", "realtime")),
    ("options.deadline=null", ("options.deadline", None)),
    ("terminal.alpha0.1=[0.1, 0]", ("terminal.alpha0.1", [0.1, 0])),
    ("options.tolerance=1e-6", ("options.tolerance", 1e-6)),
    ("name=a=b", ("name", "a=b")),
])
def test_parse_override(text, expected):
    assert parse_override(text) == expected


# --- property: random valid systems build ---------------------------------------------------------

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


@st.composite
def _subsystem(draw, name: str) -> dict:
    n, m = draw(st.integers(1, 3)), draw(st.integers(1, 2))
    mat = lambda r, c: draw(st.lists(st.lists(finite, min_size=c, max_size=c), min_size=r, max_size=r))
    lower = draw(st.lists(st.one_of(st.floats(-100, -1e-3), st.just(-float("inf"))), min_size=m, max_size=m))
    upper = draw(st.lists(st.one_of(st.floats(1e-3, 100), st.just(float("inf"))), min_size=m, max_size=m))
    q = draw(st.lists(st.floats(0, 10), min_size=n, max_size=n))
    r = draw(st.lists(st.floats(1e-3, 10), min_size=m, max_size=m))
    return {"name": name, "A": mat(n, n), "B": mat(n, m), "Q": np.diag(q).tolist(), "R": np.diag(r).tolist(),
            "input": {"lower": lower, "upper": upper}, "x0": draw(st.lists(finite, min_size=n, max_size=n))}


@st.composite
def _scenario(draw) -> dict:
    M = draw(st.integers(1, 4))
    subs = [draw(_subsystem(str(i))) for i in range(M)]
    pairs = [(i, j) for i in range(M) for j in range(M) if i != j]
    chosen = draw(st.lists(st.sampled_from(pairs), unique=True, max_size=len(pairs))) if pairs else []
    couplings = []
    for i, j in chosen:
        n_i, n_j = len(subs[i]["A"]), len(subs[j]["A"])
        A = draw(st.lists(st.lists(finite, min_size=n_j, max_size=n_j), min_size=n_i, max_size=n_i))
        couplings.append({"target": str(i), "source": str(j), "A": A})
    return {"name": "random", "subsystems": subs, "couplings": couplings}


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_scenario())
def test_random_valid_scenarios_build(data):
    scn = validate_scenario(data)
    system = build_system(scn)
    n = sum(len(s["A"]) for s in data["subsystems"])
    m = sum(len(s["B"][0]) for s in data["subsystems"])
    assert system.M == len(data["subsystems"])
    assert system.A.shape == (n, n) and system.B.shape == (n, m) and system.x0.shape == (n,)
    assert len(system.edges) == len({tuple(sorted((c["target"], c["source"]))) for c in data["couplings"]})
    for c in data["couplings"]:
        i, j = int(c["target"]), int(c["source"])
        assert np.array_equal(system.A[system.xs(i), system.xs(j)], c["A"])


def test_revision_bounds_by_index():
    from dmpc.scenario import revision_bounds

    bound = {"state": [0.1, 0.2], "input": [0.3]}
    scn = load_scenario(CHAIN, {"family.M": 3, "options.tube": "robust", "family.subsystem.revision_bound": bound})
    bounds = revision_bounds(scn)
    assert sorted(bounds) == [0, 1, 2]
    assert np.array_equal(bounds[1].state, [0.1, 0.2]) and np.array_equal(bounds[1].input, [0.3])
    assert revision_bounds(load_scenario(PAPER)) == {}
