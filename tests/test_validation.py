"""`rover check`: every problem at once, each at its FILE:LINE:COL, with did-you-mean hints."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest
from helpers import ROOT, read_bag, run_rover, write_imu_dataset

from rover.cli.registry import BUILTINS
from rover.errors import SpecError
from rover.pipeline.validation import load_and_check

GOOD = """\
version: 1
name: toy
vars: {dataset: data.mcap, output: out}
operators:
  replay: {uses: dataset_replay, params: {path: "${dataset}"}}
  heading: {uses: toyops.Heading, inputs: {imu: replay/imu, odom: replay/odom}, params: {gain: 2}}
  record: {uses: recorder, inputs: {pose: heading/pose}, params: {out: "${output}"}}
"""


def problems(tmp_path: Path, text: str, **overrides) -> list[tuple[int, int, str]]:
    path = tmp_path / "pipeline.yaml"
    path.write_text(textwrap.dedent(text))
    with pytest.raises(SpecError) as info:
        load_and_check(path, BUILTINS, overrides)
    assert all(d.file == str(path) for d in info.value.diagnostics)
    return [(d.line, d.col, d.message) for d in info.value.diagnostics]


def at(text: str, needle: str, nth: int = 0) -> tuple[int, int]:
    """1-based line and column of the nth occurrence of `needle` in `text`."""
    index = -1
    for _ in range(nth + 1):
        index = text.index(needle, index + 1)
    line = text.count("\n", 0, index) + 1
    return line, index - (text.rfind("\n", 0, index) + 1) + 1


def has(found, where, *words):
    line, col = where
    assert any(ln == line and c == col and all(w in m for w in words) for ln, c, m in found), found


def test_good_file_passes(tmp_path):
    path = tmp_path / "pipeline.yaml"
    path.write_text(GOOD)
    pipeline = load_and_check(path, BUILTINS)
    assert list(pipeline.nodes) == ["replay", "heading", "record"]
    assert pipeline.nodes["heading"].params.gain == 2.0
    assert pipeline.nodes["replay"].params.path == "data.mcap"


def test_yaml_syntax_error(tmp_path):
    found = problems(tmp_path, "version: 1\noperators:\n  a: {uses: recorder\n  b: [\n")
    assert len(found) == 1
    line, col, msg = found[0]
    assert "YAML syntax error" in msg and line == 4


def test_duplicate_key(tmp_path):
    text = GOOD + "  record: {uses: recorder}\n"
    has(problems(tmp_path, text), at(text, "record:", 1), "duplicate key 'record'")


def test_unknown_keys_everywhere(tmp_path):
    text = GOOD.replace("vars:", "varz:").replace("inputs: {pose", "input: {pose")
    text = text.replace("name: toy", "name: toy\nhosts: {nuc: {listn: [tcp/127.0.0.1:7447]}}")
    found = problems(tmp_path, text)
    has(found, at(text, "varz"), "unknown key 'varz'", "did you mean 'vars'")
    has(found, at(text, "input:"), "unknown key 'input'", "did you mean 'inputs'")
    has(found, at(text, "listn"), "unknown key 'listn'", "did you mean 'listen'")


def test_unknown_operator(tmp_path):
    text = GOOD.replace("uses: dataset_replay", "uses: dataset_replai").replace("toyops.Heading", "toyops.Headin")
    found = problems(tmp_path, text)
    has(found, at(text, "dataset_replai"), "unknown operator 'dataset_replai'", "did you mean 'dataset_replay'")
    has(found, at(text, "toyops.Headin"), "'toyops.Headin' is not an Operator class")


def test_unimportable_user_operator(tmp_path):
    text = GOOD.replace("toyops.Heading", "nolab.filters.Median")
    has(problems(tmp_path, text), at(text, "nolab"), "cannot import 'nolab.filters'")


def test_unknown_and_ill_typed_params(tmp_path):
    text = GOOD.replace("{gain: 2}", "{gian: 2}").replace('{out: "${output}"}', "{out: [1]}")
    found = problems(tmp_path, text)
    has(found, at(text, "gian"), "has no param 'gian'", "did you mean 'gain'", "(params: gain)")
    has(found, at(text, "[1]"), "param 'out' of operator 'record'", "expected str")


def test_ill_typed_param_from_set(tmp_path):
    text = GOOD.replace("{gain: 2}", '{gain: "${g}"}').replace("output: out}", "output: out, g: 1}")
    has(problems(tmp_path, text, g="fast"), at(text, '"${g}"'), "param 'gain'", "expected float, got 'fast'")


def test_unknown_input_and_output_ports(tmp_path):
    text = GOOD.replace("{imu: replay/imu", "{imuu: replay/imu").replace("odom: replay/odom", "odom: replay/odometry")
    found = problems(tmp_path, text)
    has(found, at(text, "imuu"), "has no input 'imuu'", "did you mean 'imu'", "(inputs: imu, odom)")
    has(found, at(text, "replay/odometry"), "'replay' (dataset_replay) has no output 'odometry'", "did you mean 'odom'")


def test_wire_to_unknown_operator(tmp_path):
    text = GOOD.replace("pose: heading/pose", "pose: headin/pose")
    has(problems(tmp_path, text), at(text, "headin/pose"), "unknown operator 'headin'", "did you mean 'heading'")


def test_message_type_mismatch(tmp_path):
    text = GOOD.replace("odom: replay/odom", "odom: replay/imu")
    has(
        problems(tmp_path, text),
        at(text, "replay/imu", 1),
        "type mismatch",
        "replay/imu sends sensor_msgs/msg/Imu",
        "takes nav_msgs/msg/Odometry",
    )


def test_unwired_required_input(tmp_path):
    text = GOOD.replace("imu: replay/imu, ", "")
    has(problems(tmp_path, text), at(text, "heading:"), "required input 'imu'", "not wired")


def test_cycle(tmp_path):
    text = (
        GOOD
        + "  a: {uses: toyops.Passthrough, inputs: {imu: b/imu}}\n"
        + "  b: {uses: toyops.Passthrough, inputs: {imu: a/imu}}\n"
    )
    has(problems(tmp_path, text), at(text, "a/imu"), "cycle: a <- b <- a")


def test_source_with_inputs(tmp_path):
    text = GOOD.replace('params: {path: "${dataset}"}}', 'inputs: {x: heading/pose}, params: {path: "${dataset}"}}')
    has(problems(tmp_path, text), at(text, "inputs: {x"), "is a source and takes no inputs")


def test_undeclared_host(tmp_path):
    text = GOOD.replace(
        "operators:",
        "hosts:\n  nuc: {listen: [tcp/127.0.0.1:7447]}\n  laptop: {connect: [tcp/127.0.0.1:7447]}\noperators:",
    )
    text = text.replace("uses: dataset_replay,", "uses: dataset_replay, host: nuc,")
    text = text.replace("uses: toyops.Heading,", "uses: toyops.Heading, host: laptop,")
    text = text.replace("uses: recorder,", "uses: recorder, host: laptp,")
    has(problems(tmp_path, text), at(text, "laptp"), "undeclared host 'laptp'", "did you mean 'laptop'")


def test_host_without_a_path(tmp_path):
    text = GOOD.replace(
        "operators:",
        "hosts:\n  nuc: {listen: [tcp/127.0.0.1:7447]}\n  base: {}\n"
        "  laptop: {connect: [tcp/127.0.0.1:7448]}\n  far: {listen: [tcp/127.0.0.1:7449]}\noperators:",
    )
    for op, host in (("replay", "nuc"), ("heading", "base"), ("record", "laptop")):
        text = text.replace(f"  {op}: {{", f"  {op}: {{host: {host}, ")
    found = problems(tmp_path, text)
    has(found, at(text, "base:"), "host 'base' has neither listen nor connect")
    has(found, at(text, "tcp/127.0.0.1:7448"), "connects to tcp/127.0.0.1:7448, where no declared host listens")
    has(found, at(text, "far:"), "host 'far' has no connect path")


def test_undefined_variable_and_bad_endpoint(tmp_path):
    text = GOOD.replace('path: "${dataset}"', 'path: "${datset}"')
    text = text.replace("operators:", "hosts:\n  nuc: {listen: [tcp/127.0.0.1:port]}\noperators:")
    found = problems(tmp_path, text)
    has(found, at(text, "tcp/127.0.0.1:port"), "bad endpoint 'tcp/127.0.0.1:port'")
    has(found, at(text, '"${datset}"'), "undefined variable ${datset}", "did you mean 'dataset'")


def test_every_problem_at_once(tmp_path):
    text = GOOD.replace("vars:", "varz:").replace("{gain: 2}", "{gian: 2}").replace("uses: recorder", "uses: recordr")
    assert len(problems(tmp_path, text)) >= 4


def test_cli_check_prints_positions_and_exits_2(tmp_path):
    bad = tmp_path / "bad.yaml"
    text = GOOD.replace("uses: recorder", "uses: recordr")
    bad.write_text(text)
    proc = run_rover("check", str(bad))
    assert proc.returncode == 2
    line, col = at(text, "recordr")
    assert f"{bad}:{line}:{col}: unknown operator 'recordr'; did you mean 'recorder'?" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_cli_check_good_file_one_line(tmp_path):
    good = tmp_path / "good.yaml"
    good.write_text(GOOD)
    proc = run_rover("check", str(good), str(ROOT / "pipeline.yaml"))
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 2 and all(": ok: pipeline" in line for line in lines)


def test_check_names_the_hub_the_other_hosts_depend_on(tmp_path):
    """The default file's NUC is the only listener: a single point of failure, and `rover check` says so;
    with base listening too and the laptop connecting to both, there is no hub."""
    hub = run_rover("check", str(ROOT / "pipeline.yaml"))
    assert hub.returncode == 0 and "hub nuc: base and laptop reach each other only through it" in hub.stdout
    mesh = (
        (ROOT / "pipeline.yaml")
        .read_text()
        .replace(
            'base:   {connect: ["tcp/127.0.0.1:${port}"]}',
            'base:   {listen: ["tcp/127.0.0.1:7448"], connect: ["tcp/127.0.0.1:${port}"]}',
        )
    )
    mesh = mesh.replace(
        'laptop: {connect: ["tcp/127.0.0.1:${port}"]}',
        'laptop: {connect: ["tcp/127.0.0.1:${port}", "tcp/127.0.0.1:7448"]}',
    )
    (tmp_path / "mesh.yaml").write_text(mesh)
    checked = run_rover("check", str(tmp_path / "mesh.yaml"))
    assert checked.returncode == 0 and ": ok:" in checked.stdout and "; hub" not in checked.stdout


def test_cli_missing_file(tmp_path):
    proc = run_rover("check", str(tmp_path / "nope.yaml"))
    assert proc.returncode == 2 and "nope.yaml: no such file" in proc.stderr


BAD_VALUES = """\
version: 1
name: toy
vars: {port: 99999}
hosts:
  nuc: {listen: ["tcp/127.0.0.1:${port}"], connect_timeout_s: .inf, host_timeout_s: -3}
  laptop: {connect: ["tcp/127.0.0.1:7447"], connect_timeout_s: 0, wait_timeout_s: soon}
operators:
  replay: {uses: dataset_replay, host: nuc, params: {path: data.mcap, speed: -1}}
  sweep: {uses: channel_sweep, host: laptop, inbox: 0, inputs: {frames: replay/csi, setup: replay/setup},
          params: {dwell_s: 0}}
"""


def test_check_rejects_out_of_range_values_with_their_positions(tmp_path):
    path = tmp_path / "pipeline.yaml"
    path.write_text(BAD_VALUES)
    proc = run_rover("check", str(path))
    assert proc.returncode == 2
    lines = proc.stderr.splitlines()

    def reported(needle: str, *words: str) -> None:
        line, col = at(BAD_VALUES, needle)
        assert any(x.startswith(f"{path}:{line}:{col}: ") and all(w in x for w in words) for x in lines), lines

    reported('"tcp/127.0.0.1:${port}"', "port 99999 is outside 1-65535")
    reported(".inf", "connect_timeout_s", "finite")
    reported("0, wait", "connect_timeout_s", "must be > 0")
    reported("-3}", "host_timeout_s", "must be >= 1 and <= 3600")
    reported("soon}", "wait_timeout_s")
    reported("0, inputs", "inbox", "must be > 0")
    reported("-1}", "param 'speed' of operator 'replay'", "float > 0", "got -1")
    reported("0}}\n", "param 'dwell_s' of operator 'sweep'", "must be > 0")


def test_check_rejects_a_rig_with_nan_antenna_positions(tmp_path):
    text = (
        "receiver: {antenna_positions_m: [[0, 0], [.nan, 0.02]]}\n"
        "excitation: {channel: 165}\ntags: [{id: 1, channel: 149}]\n"
    )
    path = tmp_path / "setup.yaml"
    path.write_text(text)
    proc = run_rover("check", str(path))
    line, col = at(text, "[.nan")
    assert (
        proc.returncode == 2
        and f"{path}:{line}:{col}: antenna 1 position must be a list of finite numbers" in proc.stderr
    )


def test_set_operator_param_is_typed_and_validated(tmp_path):
    path = tmp_path / "pipeline.yaml"
    path.write_text(GOOD)
    pipeline = load_and_check(path, BUILTINS, {"heading.gain": 3, "record.file": "x.mcap", "output": "o"})
    assert pipeline.nodes["heading"].params.gain == 3.0 and pipeline.nodes["record"].params.file == "x.mcap"
    assert pipeline.spec.command_line() == {
        "vars": {"output": "o"},
        "params": {"heading.gain": 3, "record.file": "x.mcap"},
    }
    assert pipeline.nodes["heading"].build().context.command_line["params"] == {
        "heading.gain": 3,
        "record.file": "x.mcap",
    }


def test_set_operator_param_errors_name_the_operator_in_the_file(tmp_path):
    found = problems(tmp_path, GOOD, **{"heading.gian": 3, "hedaing.gain": 1, "heading.gain": "x"})
    has(found, at(GOOD, "heading:"), "--set heading.gian=3", "has no param 'gian'", "did you mean 'gain'")
    has(found, at(GOOD, "gain: 2"), "--set heading.gain='x'", "param 'gain' of operator 'heading'", "expected float")
    has(found, at(GOOD, "operators:"), "--set hedaing.gain", "no operator 'hedaing'", "did you mean 'heading'")


@pytest.mark.parametrize("item", ["slam.=1", ".wheel=1", "slam.a-b=1", "no_equals_sign"])
def test_set_with_a_malformed_name_is_one_line_and_status_2(item):
    proc = run_rover("run", "--set", item)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "--set" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_set_reaches_check_graph_and_run(tmp_path):
    assert run_rover("check", str(ROOT / "pipeline.yaml"), "--set", "slam.wheel=false").returncode == 0
    proc = run_rover("graph", str(ROOT / "pipeline.yaml"), "--set", "slam.window=1")
    assert proc.returncode == 2 and "--set slam.window=1" in proc.stderr and "must be >= 2" in proc.stderr


FAN = GOOD.replace(
    "  record: {uses: recorder, inputs: {pose: heading/pose}",
    "  fan: {uses: toyops.Fan, inputs: {imu: replay/imu}, params: {outputs: {a: sensor_msgs/msg/Imu}}}\n"
    "  record: {uses: recorder, inputs: {pose: heading/pose, a: fan/a}",
)


def test_ports_declared_by_params_are_checked_like_declared_ones(tmp_path):
    """An operator whose outputs its params name (toyops.Fan, as a ROS 2 bridge's topics): wiring
    to a declared one passes; to an undeclared one is 'has no output' listing the declared ones;
    a declared type that does not fit the input is a type mismatch."""
    path = tmp_path / "fan.yaml"
    path.write_text(FAN)
    pipeline = load_and_check(path, BUILTINS)
    assert pipeline.nodes["fan"].output_type("a") == "sensor_msgs/msg/Imu"
    text = FAN.replace("a: fan/a}", "a: fan/b}")
    has(problems(tmp_path, text), at(text, "fan/b"), "'fan' (toyops.Fan) has no output 'b'", "(outputs: a)")
    text = FAN.replace(
        "heading: {uses: toyops.Heading, inputs: {imu: replay/imu",
        "heading: {uses: toyops.Heading, inputs: {imu: fan/a",
    ).replace("{a: sensor_msgs/msg/Imu}", "{a: nav_msgs/msg/Odometry}")
    has(problems(tmp_path, text), at(text, "fan/a"), "type mismatch", "fan/a sends nav_msgs/msg/Odometry")


def test_bad_ports_declared_by_params_are_one_line_each_at_the_params(tmp_path):
    """An unknown message type, a bad port name, or params the operator refuses (no outputs): one
    problem at the operator's params, naming what is wrong."""
    text = FAN.replace("{a: sensor_msgs/msg/Imu}", "{a: sensor_msgs/msg/Imuu, 9b: sensor_msgs/msg/Imu}")
    found = problems(tmp_path, text)
    has(found, at(text, "params: {outputs"), "declares output 'a': unknown message type 'sensor_msgs/msg/Imuu'")
    has(found, at(text, "params: {outputs"), "declares output name '9b'")
    text = FAN.replace("{a: sensor_msgs/msg/Imu}", "{}")
    has(problems(tmp_path, text), at(text, "params: {outputs"), "param 'outputs' declares no output port")


def test_a_run_sends_on_ports_declared_by_params(tmp_path):
    """One process: the fan's declared output reaches the recorder, message for message."""
    dataset = write_imu_dataset(tmp_path / "toy.mcap", 200)
    path = tmp_path / "fan.yaml"
    path.write_text(FAN)
    out = tmp_path / "out"
    run_rover("run", str(path), "--dataset", str(dataset), "--output", str(out), check=True)
    topics = [t for t, _s, _d in read_bag(out / "results.mcap")]
    assert topics.count("/a") == 200


TWO_HOSTS = """\
version: 1
name: toy
hosts:
  robot: {listen: ["tcp/127.0.0.1:7447"]}
  desk: {connect: ["tcp/127.0.0.1:7447"]}
operators:
  replay: {uses: dataset_replay, host: robot, params: {path: data.mcap}}
  ticks: {uses: toyops.Ticker, host: desk}
  heading: {uses: toyops.Heading, inputs: {imu: replay/imu, odom: replay/odom}}
  record: {uses: recorder, inputs: {pose: heading/pose}, params: {out: out}}
"""


def test_an_operator_without_a_host_runs_where_its_inputs_come_from(tmp_path):
    """As an operator added to the default pipeline without a host: through a chain of such operators too."""
    path = tmp_path / "pipeline.yaml"
    path.write_text(TWO_HOSTS)
    nodes = load_and_check(path, BUILTINS).nodes
    assert (nodes["heading"].spec.host, nodes["record"].spec.host) == ("robot", "robot")


def test_an_operator_without_a_host_fed_from_two_hosts_must_say_where_it_runs(tmp_path):
    text = TWO_HOSTS.replace("inputs: {pose: heading/pose}", "inputs: {pose: heading/pose, imu: ticks/imu}")
    found = problems(tmp_path, text)
    has(found, at(text, "record:"), "operator 'record' has no host: (hosts: robot, desk)", "from several (desk, robot)")
