"""Limits on YAML input (issue 13, item 2): alias bombs, deep nesting, huge files and long
operator chains end as one clean `FILE: message` line and status 2, never a traceback."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest
import yaml
from helpers import ROOT, T0_NS
from hypothesis import given, settings
from hypothesis import strategies as st

from rover.cli.app import main
from rover.datasets.scenario import load_scenario
from rover.formats.bag import BagWriter
from rover.messages import header, make
from rover.pipeline import yamlpos
from rover.pipeline.yamlpos import (
    MAX_YAML_BYTES,
    MAX_YAML_DEPTH,
    MAX_YAML_NODES,
    YamlLimitError,
    load,
    parse_scalar,
    safe_load_limited,
)

EXIT_BAD_INPUT = 2
PIPELINE = """\
version: 1
operators:
  replay: {uses: dataset_replay, params: {path: data.mcap}}
  record: {uses: recorder, inputs: {imu: replay/imu}, params: {out: out}}
"""
SETUP = "receiver: {antenna_positions_m: [[0, 0], [0.0258, 0]]}\nexcitation: {channel: 165}\n"


def alias_bomb(levels: int) -> str:
    """'Billion laughs': each level lists the one below nine times, 9**levels strings in all."""
    lines = ['lol0: &lol0 ["lol"]']
    for i in range(1, levels + 1):
        lines.append(f"lol{i}: &lol{i} [" + ", ".join([f"*lol{i - 1}"] * 9) + "]")
    return "\n".join(lines) + "\n"


def nested(depth: int) -> str:
    return "[" * depth + "]" * depth


def check(path: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> str:
    """`rover check PATH`, in process: status 2 and exactly one problem; returns that line."""
    assert main(["check", str(path), *extra]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 2 and lines[1] == "1 problem found", err
    return lines[0]


def names_file(line: str, path: Path) -> None:
    assert line.startswith(f"{path}:"), line


@pytest.mark.parametrize("kind", ["pipeline", "setup"])
@pytest.mark.parametrize("levels", [9, 7])
def test_alias_bomb_is_rejected(tmp_path, capsys, kind, levels):
    path = tmp_path / f"{kind}.yaml"
    path.write_text((PIPELINE if kind == "pipeline" else SETUP) + alias_bomb(levels))
    line = check(path, capsys)
    names_file(line, path)
    assert f"YAML aliases expand to more than {MAX_YAML_NODES:,} nodes (an alias bomb?)" in line


def test_alias_bomb_as_a_mapping_key_is_not_expanded(tmp_path, capsys):
    path = tmp_path / "pipeline.yaml"
    path.write_text(PIPELINE + 'lol0: &lol0 ["lol"]\n? [*lol0, *lol0]\n: 1\n')
    line = check(path, capsys)
    names_file(line, path)
    assert "mapping keys must be plain scalars" in line


def test_recursive_alias_is_rejected(tmp_path, capsys):
    path = tmp_path / "pipeline.yaml"
    path.write_text(PIPELINE + "loop: &loop [*loop]\n")
    line = check(path, capsys)
    names_file(line, path)
    assert f"YAML nested deeper than {MAX_YAML_DEPTH} levels (through aliases)" in line


@pytest.mark.parametrize("depth", [900, 100_000])
def test_deep_nesting_in_a_file_is_rejected(tmp_path, capsys, depth):
    path = tmp_path / "pipeline.yaml"
    path.write_text(PIPELINE + f"deep: {nested(depth)}\n")
    line = check(path, capsys)
    names_file(line, path)
    assert f"YAML nested deeper than {MAX_YAML_DEPTH} levels" in line


def test_deep_block_nesting_in_a_file_is_rejected(tmp_path, capsys):
    path = tmp_path / "pipeline.yaml"
    path.write_text(PIPELINE + "".join(f"{'  ' * i}k{i}:\n" for i in range(900)))
    line = check(path, capsys)
    assert line.startswith(f"{path}:{MAX_YAML_DEPTH + 5}:"), line
    assert f"YAML nested deeper than {MAX_YAML_DEPTH} levels" in line


@pytest.mark.parametrize("depth", [900, 100_000])
def test_deep_nesting_in_set_is_rejected(tmp_path, capsys, depth):
    path = tmp_path / "pipeline.yaml"
    path.write_text(PIPELINE)
    line = check(path, capsys, "--set", f"x={nested(depth)}")
    assert line == f"--set x: YAML nested deeper than {MAX_YAML_DEPTH} levels"


def test_nesting_up_to_the_limit_is_accepted():
    deepest = nested(MAX_YAML_DEPTH - 1)  # inside the top-level mapping: MAX_YAML_DEPTH levels
    assert load(f"a: {deepest}", "f.yaml").data == {"a": json.loads(deepest)}
    with pytest.raises(YamlLimitError):
        load(f"a: [{deepest}]", "f.yaml")
    assert parse_scalar(nested(MAX_YAML_DEPTH)) == json.loads(nested(MAX_YAML_DEPTH))


def test_1500_operators_listed_downstream_first_are_accepted(tmp_path, capsys):
    n = 1500
    lines = ["version: 1", "operators:"]
    for i in range(n):
        source = f"op{i + 1}" if i + 1 < n else "replay"
        lines.append(f"  op{i}: {{uses: toyops.Passthrough, inputs: {{imu: {source}/imu}}}}")
    lines.append("  replay: {uses: dataset_replay, params: {path: data.mcap}}")
    path = tmp_path / "long.yaml"
    path.write_text("\n".join(lines) + "\n")
    assert main(["check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert err == "" and f"{n + 1} operators, {n} wires" in out


def test_cycle_in_a_long_chain_is_still_found(tmp_path, capsys):
    n = 1200  # longer than Python's 1,000 frames
    lines = ["version: 1", "operators:"]
    for i in range(n):
        lines.append(f"  op{i}: {{uses: toyops.Passthrough, inputs: {{imu: op{(i + 1) % n}/imu}}}}")
    path = tmp_path / "loop.yaml"
    path.write_text("\n".join(lines) + "\n")
    line = check(path, capsys)
    names_file(line, path)
    assert "cycle: op0 <- op1 <- op2" in line and line.endswith("op0 (a pipeline must be acyclic)")


def test_50_mb_file_is_rejected_unread(tmp_path, capsys):
    path = tmp_path / "pipeline.yaml"
    with path.open("wb") as f:
        f.write(PIPELINE.encode())
        f.truncate(50 * 2**20)
    line = check(path, capsys)
    assert line == f"{path}: 52,428,800 bytes: larger than the 1 MiB a YAML input may be"


def test_large_text_is_rejected(tmp_path):
    text = "# " + "x" * MAX_YAML_BYTES + "\n"
    with pytest.raises(YamlLimitError, match="bytes: larger than the 1 MiB"):
        load(text, "setup.yaml")
    scenario = tmp_path / "big.yaml"
    scenario.write_text(text)
    with pytest.raises(YamlLimitError) as info:
        load_scenario(str(scenario))
    assert info.value.diagnostics[0].file == str(scenario)


def test_too_many_nodes_without_aliases(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(yamlpos, "MAX_YAML_NODES", 1000)  # parsing 100,000 real nodes takes seconds
    path = tmp_path / "pipeline.yaml"
    path.write_text(PIPELINE + "many: [" + ",".join(["0"] * 1000) + "]\n")
    line = check(path, capsys)
    names_file(line, path)
    assert "YAML has more than 1,000 nodes" in line


def test_scenario_set_is_limited():
    with pytest.raises(YamlLimitError) as info:
        load_scenario("paper", {"room.size_m": nested(900)})
    assert str(info.value) == f"--set room.size_m: YAML nested deeper than {MAX_YAML_DEPTH} levels"


def test_safe_load_limited_is_safe_load_within_the_limits():
    text = "a: [1, 2.5, x, null, true]\nb: {c: 2024-01-01}\nd: !!set {x, y}\n"
    assert safe_load_limited(text, "meta") == yaml.safe_load(text)
    assert safe_load_limited("", "meta") is None
    with pytest.raises(YamlLimitError, match="alias bomb"):
        safe_load_limited(alias_bomb(9), "meta")


@pytest.mark.parametrize("as_json", [False, True])
def test_alias_bomb_in_dataset_metadata(tmp_path, capsys, as_json):
    path = tmp_path / "d.mcap"
    with BagWriter(path, metadata={"rover.simulation": {"yaml": alias_bomb(9)}}) as bag:
        bag.write("/imu/data", make("sensor_msgs/msg/Imu", header=header(T0_NS)), T0_NS)
    assert main(["info", str(path), *(["--json"] if as_json else [])]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err == (
        f"rover: error: {path}: metadata record 'rover.simulation', line 1: "
        f"YAML aliases expand to more than {MAX_YAML_NODES:,} nodes (an alias bomb?)\n"
    )


def check_never_raises(path: Path, text: str) -> None:
    """`rover check` of any text: status 0 or 2, and on 2 every problem line names the file."""
    path.write_text(text, encoding="utf-8")
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        status = main(["check", str(path)])
    assert status in (0, EXIT_BAD_INPUT)
    if status == EXIT_BAD_INPUT:
        *problems, summary = err.getvalue().splitlines()
        assert summary.endswith(" found") and problems
        assert all(line.startswith(f"{path}:") for line in problems), problems


@settings(max_examples=100, deadline=None)
@given(text=st.text())
def test_check_of_arbitrary_text_never_raises(tmp_path_factory, text):
    check_never_raises(tmp_path_factory.getbasetemp() / "text.yaml", text)


@settings(max_examples=100, deadline=None)
@given(data=st.binary())
def test_check_of_arbitrary_bytes_never_raises(tmp_path_factory, data):
    check_never_raises(tmp_path_factory.getbasetemp() / "bytes.yaml", data.decode("utf-8", errors="replace"))


@pytest.mark.parametrize(
    ("text", "value"), [("1e9", 1e9), ("1E-3", 1e-3), ("-2.5e+4", -2.5e4), (".5e1", 5.0), ("1_000e2", 1e5)]
)
def test_a_float_with_an_exponent_is_a_float_as_python_reads_it(text, value):
    assert parse_scalar(text) == value and isinstance(parse_scalar(text), float)
    assert load(f"x: {text}\n", "f.yaml").data == {"x": value}


@pytest.mark.parametrize("text", ["1e", "e9", "1e9x", "0x1p3"])
def test_text_that_only_looks_like_an_exponent_stays_text(text):
    assert parse_scalar(text) == text


def test_exponent_floats_reach_params_from_files_and_the_command_line(capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    from rover.datasets.scenario import load_scenario

    assert load_scenario("paper", {"receiver.dwell_s": "5e-2"}).receiver.dwell_s == 0.05
    assert main(["check", "pipeline.yaml", "--set", "slam.huber_sigma=1e0"]) == 0, capsys.readouterr().err
    assert main(["check", "pipeline.yaml", "--set", "slam.huber_sigma=1e0x"]) == 2
