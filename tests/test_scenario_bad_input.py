"""Malformed scenarios: always a one-line ScenarioError that names the field at fault."""
from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmpc.scenario import ScenarioError, load_scenario, parse_override, validate_scenario

ROOT = Path(__file__).resolve().parents[1]
BAD = Path(__file__).resolve().parent / "data" / "bad_scenarios"
PAPER = ROOT / "scenarios" / "paper.yaml"
CHAIN = ROOT / "scenarios" / "chain.yaml"

# file -> substrings the message must contain (the first one names the field at fault)
EXPECTED = {
    "wrong_matrix_shape.yaml": ["subsystems[1].A:", "expected a 2x2 matrix, got 2x3"],
    "non_numeric_entry.yaml": ["subsystems[0].Q[0][1]:", "'abc'"],
    "nan_entry.yaml": ["subsystems[0].B[0][0]:", "NaN"],
    "inf_entry.yaml": ["subsystems[0].A[0][0]:", "finite"],
    "ragged_matrix.yaml": ["subsystems[0].A:", "different lengths"],
    "unknown_field.yaml": ["options.iteratons:", "unknown field", "iterations"],
    "missing_required.yaml": ["subsystems[1].R:", "required"],
    "coupling_unknown_source.yaml": ["couplings[1].source:", "unknown subsystem '7'"],
    "graph_unknown_neighbour.yaml": ["graph[0][1]:", "unknown subsystem '9'"],
    "q_not_psd.yaml": ["subsystems[0].Q:", "positive semidefinite"],
    "q_not_symmetric.yaml": ["subsystems[0].Q:", "symmetric"],
    "r_not_pd.yaml": ["subsystems[1].R:", "positive definite"],
    "p_not_pd.yaml": ["subsystems[0].P:", "positive definite"],
    "k_missing_given.yaml": ["subsystems[1].K:", "required when design.gains is 'given'"],
    "k_wrong_shape.yaml": ["subsystems[0].K:", "expected a 1x2 matrix, got 2x1"],
    "x0_wrong_length.yaml": ["subsystems[0].x0:", "expected 2 entries", "got 3"],
    "bounds_wrong_order.yaml": ["subsystems[0].input.lower[0]:", "greater than upper"],
    "input_origin_not_interior.yaml": ["subsystems[1].input.lower[0]:", "origin in its interior"],
    "state_polytope_origin_outside.yaml": ["subsystems[0].state.h[1]:", "origin in its interior"],
    "duplicate_names.yaml": ["subsystems[1].name:", "duplicate subsystem name '1'"],
    "duplicate_key.yaml": ["duplicate_key.yaml:", "line 7", "duplicate key 'A'"],
    "python_tag.yaml": ["python_tag.yaml:", "!!python/object/apply:os.system", "not allowed"],
    "tab_garbage.yaml": ["tab_garbage.yaml:", "not valid YAML", "line 1"],
    "binary.yaml": ["binary.yaml:", "not a YAML text file"],
    "latin1.yaml": ["latin1.yaml:", "not a UTF-8 text file"],
    "empty.yaml": ["empty.yaml:", "empty"],
    "comments_only.yaml": ["comments_only.yaml:", "empty"],
    "top_level_list.yaml": ["top_level_list.yaml:", "mapping", "got list"],
    "both_family_and_subsystems.yaml": ["family:", "not both"],
    "family_x0_wrong_length.yaml": ["family.x0_cycle[1]:", "expected 2 entries"],
    "coupling_b_wrong_shape.yaml": ["couplings[1].B:", "expected a 2x1 matrix, got 1x1"],
    "alpha0_wrong_length.yaml": ["terminal.alpha0.1:", "expected 2 entries"],
    "tube_robust_without_revision_bound.yaml": ["subsystems[1].revision_bound:", "robust"],
    "loss_out_of_range.yaml": ["faults.loss:", "1.5"],
    "loss_without_deadline.yaml": ["faults.loss:", "lost messages need a deadline in lockstep mode"],
    "link_unknown_endpoint.yaml": ["faults.links[0].target:", "'5'"],
    "horizon_zero.yaml": ["horizon:", "greater than or equal to 1"],
    "recursive_alias.yaml": ["recursive_alias.yaml:", "recursive"],
}


def _message(path, overrides=None) -> str:
    with pytest.raises(ScenarioError) as info:
        load_scenario(path, overrides)
    message = str(info.value)
    assert "\n" not in message, message
    return message


def test_every_bad_file_has_an_expectation():
    files = {p.name for p in BAD.iterdir()}
    assert files == set(EXPECTED)
    assert len(files) >= 14


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_bad_file_names_the_field(name):
    message = _message(BAD / name)
    for part in EXPECTED[name]:
        assert part in message, f"{part!r} not in {message!r}"
    if not message.startswith(str(BAD)):
        assert message.startswith(EXPECTED[name][0])


@pytest.mark.parametrize("name", ["missing_required.yaml", "coupling_unknown_source.yaml", "r_not_pd.yaml"])
def test_error_field_attribute(name):
    with pytest.raises(ScenarioError) as info:
        load_scenario(BAD / name)
    assert info.value.field == EXPECTED[name][0].rstrip(":")


def test_validate_refuses_what_simulate_refuses(monkeypatch, capsys, tmp_path):
    """A scenario that cannot run is not called valid: loss without a deadline, in the file or on a link."""
    from tests.helpers.cli import call, one_error_line

    cases = [(str(BAD / "loss_without_deadline.yaml"), []),
             (str(PAPER), ["--set", "faults.links=[{source: 2, target: 3, loss: 0.1}]"])]
    for path, extra in cases:
        code, _, err = call(monkeypatch, capsys, "validate", path, *extra)
        assert code == 2, err
        refused = one_error_line(err)
        assert "lost messages need a deadline" in refused
        code, _, err = call(monkeypatch, capsys, "simulate", path, *extra, "--out", str(tmp_path / "r"), "--quiet")
        assert code == 2 and one_error_line(err) == refused
    code, out, err = call(monkeypatch, capsys, "validate", str(PAPER), "--set", "faults.loss=0.1", "--set",
                          "options.deadline=0.05")
    assert code == 0, err


def test_python_tag_is_not_executed(tmp_path):
    marker = tmp_path / "pwned"
    scenario = tmp_path / "evil.yaml"
    scenario.write_text(f'name: !!python/object/apply:os.system ["touch {marker}"]\n')
    _message(scenario)
    assert not marker.exists()


def test_missing_file_and_directory(tmp_path):
    assert "cannot read" in _message(tmp_path / "nope.yaml")
    assert "cannot read" in _message(tmp_path)


def test_neither_subsystems_nor_family(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("name: x\nhorizon: 3\n")
    assert _message(path).startswith("subsystems: required")


def test_alias_bomb(tmp_path):
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, "
              f"*a{i - 1}, *a{i - 1}, *a{i - 1}]" for i in range(1, 9)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    assert "too large" in _message(path)


@pytest.mark.parametrize("overrides, expected", [
    ({"family.X": 3}, "family.X: no such field"),
    ({"family.subsystem.A.x": 3}, "family.subsystem.A.x: no such field"),
    ({"optionz.iterations": 3}, "optionz: no such field"),
    ({"family.x0_cycle[9]": [1.0, 2.0]}, "family.x0_cycle[9]: index out of range"),
    ({"family.M": 0}, "family.M: input should be greater than or equal to 1"),
    ({"family.M": "eight"}, "family.M: input should be a valid integer"),
    ({"family.M": 2.5}, "family.M:"),
    ({"horizon.x": 1}, "horizon.x: no such field"),
    ({"a..b": 1}, "a..b: invalid override path"),
    ({"family.subsystem.Q": [[1, 0], [0, -1]]}, "family.subsystem.Q: must be positive semidefinite"),
    ({"subsystems[0].x0": [1.0, 2.0]}, "subsystems: no list to index in the file"),
])
def test_bad_overrides(overrides, expected):
    message = _message(CHAIN, overrides)
    assert message.startswith(expected), message


def test_override_value_errors_mention_the_override():
    assert "(value set by override family.M)" in _message(CHAIN, {"family.M": -1})


@pytest.mark.parametrize("text", ["family.M", "=3", "family.M=[1,", "x=!!python/name:os.system", "a.b[x]=1"])
def test_bad_parse_override(text):
    with pytest.raises(ScenarioError) as info:
        parse_override(text)
    assert "\n" not in str(info.value)


def test_tube_robust_with_revision_bounds_is_accepted():
    bound = {"state": [0.01, 0.01], "input": [0.01]}
    scn = load_scenario(CHAIN, {"options.tube": "robust", "family.subsystem.revision_bound": bound})
    assert scn.options.tube == "robust"
    message = _message(CHAIN, {"options.tube": "robust"})
    assert message.startswith("family.subsystem.revision_bound: required when options.tube is 'robust'")


# --- fuzzing: anything goes in, only ScenarioError comes out ------------------------------------------

junk = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=12,
)
PAPER_DATA = yaml.safe_load(PAPER.read_text())


def _leaves(obj, path=()):
    if isinstance(obj, dict):
        for key, value in obj.items():
            yield from _leaves(value, path + (key,))
    elif isinstance(obj, list):
        for i, value in enumerate(obj):
            yield from _leaves(value, path + (i,))
    yield path


LEAVES = list(_leaves(PAPER_DATA))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(LEAVES), junk)
def test_mutated_paper_gives_scenario_or_scenario_error(path, value):
    data = copy.deepcopy(PAPER_DATA)
    if not path:
        data = value
    else:
        node = data
        for seg in path[:-1]:
            node = node[seg]
        node[path[-1]] = value
    try:
        validate_scenario(data)
    except ScenarioError as exc:
        assert "\n" not in str(exc)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode)))
def test_random_bytes_give_scenario_error(tmp_path, raw):
    path = tmp_path / "fuzz.yaml"
    path.write_bytes(raw)
    with pytest.raises(ScenarioError):
        load_scenario(path)
