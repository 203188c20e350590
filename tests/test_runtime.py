"""The runtime on real Zenoh sessions: one process or one process per host, same bytes out."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh
from helpers import free_port, popen_rover, read_bag, run_rover, write_imu_dataset

from rover.messages import cdr_stamp_ns, deserialize, header, make, serialize
from rover.transport import codec, keys

TOY = """\
version: 1
name: toy
vars: {dataset: "", output: out, port: 7447}
hosts:
  a: {listen: ["tcp/127.0.0.1:${port}"]}
  b: {connect: ["tcp/127.0.0.1:${port}"]}
  c: {connect: ["tcp/127.0.0.1:${port}"]}
operators:
  replay:  {uses: dataset_replay, host: a, params: {path: "${dataset}"}}
  heading: {uses: toyops.Heading, host: b, inputs: {imu: replay/imu, odom: replay/odom}, params: {gain: 1.5}}
  record:  {uses: recorder, host: c, inputs: {pose: heading/pose, imu: replay/imu}, params: {out: "${output}"}}
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return write_imu_dataset(tmp_path_factory.mktemp("data") / "toy.mcap", 4000)


WAIT_S = 60.0
"""The longest a test waits for a process to start listening, become ready or send enough messages."""


def client(port: int) -> zenoh.Session:
    """A Zenoh client of the rover process that listens on `port`; it waits for the process to listen."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/timeout_ms", str(int(WAIT_S * 1000)))
    conf.insert_json5("connect/exit_on_failure", "true")
    conf.insert_json5("connect/retry", '{"period_init_ms": 50, "period_max_ms": 200, "period_increase_factor": 1.5}')
    return zenoh.open(conf)


def wait_for(event: threading.Event, proc: subprocess.Popen) -> bool:
    """Wait for `event` while the process runs, at most WAIT_S; False when it exited or time ran out."""
    deadline = time.monotonic() + WAIT_S
    while not event.wait(0.1):
        if proc.poll() is not None or time.monotonic() > deadline:
            return False
    return True


def ready_event(session: zenoh.Session, pipeline: str, host: str) -> tuple[zenoh.Subscriber, threading.Event]:
    """An event set once the host declares its `ready` token, which it does after declaring its subscribers."""
    ready = threading.Event()
    key = f"{keys.PREFIX}/{pipeline}/{keys.HOSTS}/{host}/*/*/ready"
    return session.liveliness().declare_subscriber(key, lambda _sample: ready.set(), history=True), ready


def data_event(session: zenoh.Session, key: str, wanted: int) -> tuple[zenoh.Subscriber, threading.Event]:
    """An event set once `wanted` data samples (not watermarks or ends) arrived on `key`."""
    count = [0]
    enough = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        att = sample.attachment
        kind, _stamp, _mark = codec.read_attachment(att.to_bytes() if att is not None else None)
        count[0] += kind == codec.Kind.DATA
        if count[0] >= wanted:
            enough.set()

    return session.declare_subscriber(key, on_sample), enough


def run_hosts(pipeline: Path, hosts: list[str], *args: str, timeout: float = 120) -> list[tuple[int, str]]:
    procs = [popen_rover("run", str(pipeline), "--host", h, *args) for h in hosts]
    results = []
    for proc in procs:
        _out, err = proc.communicate(timeout=timeout)
        results.append((proc.returncode, err))
    return results


@pytest.mark.slow
def test_three_hosts_give_the_same_bytes_as_one_process(tmp_path, dataset):
    pipeline = tmp_path / "toy.yaml"
    pipeline.write_text(TOY)
    single = run_rover("run", str(pipeline), "--dataset", str(dataset), "--output", str(tmp_path / "one"))
    assert single.returncode == 0, single.stderr
    port = str(free_port())
    results = run_hosts(
        pipeline,
        ["c", "b", "a"],
        "--dataset",
        str(dataset),
        "--output",
        str(tmp_path / "three"),
        "--set",
        f"port={port}",
    )
    assert all(rc == 0 for rc, _ in results), results
    one = (tmp_path / "one" / "results.mcap").read_bytes()
    three = (tmp_path / "three" / "results.mcap").read_bytes()
    messages = read_bag(tmp_path / "one" / "results.mcap")
    assert sum(t == "/pose" for t, _, _ in messages) == 400
    assert sum(t == "/imu" for t, _, _ in messages) == 4000
    assert one == three


@pytest.mark.slow
def test_100k_messages_between_two_processes_none_lost_in_order(tmp_path):
    dataset = write_imu_dataset(tmp_path / "big.mcap", 100_000, odom_every=0)
    pipeline = tmp_path / "two.yaml"
    port = free_port()
    pipeline.write_text(f"""\
name: two
hosts:
  robot: {{listen: ["tcp/127.0.0.1:{port}"]}}
  laptop: {{connect: ["tcp/127.0.0.1:{port}"]}}
operators:
  replay: {{uses: dataset_replay, host: robot, params: {{path: "{dataset}"}}}}
  record: {{uses: recorder, host: laptop, inputs: {{imu: replay/imu}}, params: {{out: "{tmp_path / "out"}"}}}}
""")
    results = run_hosts(pipeline, ["laptop", "robot"], timeout=300)
    assert all(rc == 0 for rc, _ in results), results
    sent = [data for _t, _s, data in read_bag(dataset)]
    got = read_bag(tmp_path / "out" / "results.mcap")
    assert len(got) == 100_000
    assert [data for _t, _s, data in got] == sent
    stamps = [cdr_stamp_ns(data) for _t, _s, data in got]
    assert stamps == sorted(stamps)


LIVE = """\
name: live
vars: {output: out, count: 0, port: 7447}
hosts:
  robot: {listen: ["tcp/127.0.0.1:${port}"]}
operators:
  tick:   {uses: toyops.Ticker, host: robot, params: {rate_hz: 50, count: "${count}"}}
  pass:   {uses: toyops.Passthrough, host: robot, inputs: {imu: tick/imu}}
  record: {uses: recorder, host: robot, inputs: {imu: pass/imu}, params: {out: "${output}"}}
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_live_run_stops_cleanly_on_a_signal(tmp_path, sig):
    """Stopped once 25 messages went through (a client watches them), it keeps at least 20 of them."""
    pipeline = tmp_path / "live.yaml"
    pipeline.write_text(LIVE)
    port = free_port()
    out = str(tmp_path / "out")
    proc = popen_rover("run", str(pipeline), "--host", "robot", "--output", out, "--set", f"port={port}")
    with client(port) as watcher:
        _sub, flowing = data_event(watcher, "rover/live/pass/imu", 25)
        started = wait_for(flowing, proc)
    assert started and proc.poll() is None, proc.communicate()
    sent = time.monotonic()
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=10)
    took = time.monotonic() - sent
    assert proc.returncode in (0, 128 + sig), err
    assert took < 2.0, f"took {took:.2f} s to stop"
    assert "Traceback" not in err
    assert len(read_bag(tmp_path / "out" / "results.mcap")) > 20


def test_ctrl_c_before_the_first_message_is_status_130_with_empty_outputs(tmp_path):
    """The source still waits for its device (no message yet) when the user gives up."""
    pipeline = tmp_path / "live.yaml"
    pipeline.write_text(LIVE.replace('count: "${count}"}', 'count: "${count}", delay_s: 600}'))
    port = free_port()
    proc = popen_rover(
        "run", str(pipeline), "--host", "robot", "--output", str(tmp_path / "out"), "--set", f"port={port}"
    )
    with client(port) as watcher:
        _token, ready = ready_event(watcher, "live", "robot")
        assert wait_for(ready, proc), proc.communicate()
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=10)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "error" not in err, err
    assert read_bag(tmp_path / "out" / "results.mcap") == []


def test_ctrl_c_while_waiting_for_the_other_hosts_is_status_130(tmp_path, dataset):
    """Host a listens and waits for b and c, which never come; the user gives up."""
    pipeline = tmp_path / "toy.yaml"
    pipeline.write_text(TOY)
    port = free_port()
    proc = popen_rover(
        "run", str(pipeline), "--host", "a", "--dataset", str(dataset), "--set", f"port={port}", cwd=tmp_path
    )
    with client(port) as watcher:
        _token, ready = ready_event(watcher, "toy", "a")
        assert wait_for(ready, proc), proc.communicate()
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=10)
    assert proc.returncode == 130, err
    assert time.monotonic() - sent < 2.0
    assert "Traceback" not in err and "error" not in err, err


def test_an_output_that_cannot_be_written_fails_the_run_and_leaves_no_other_output(tmp_path):
    """One writer fails at the end (its file's path is a folder): status 1, one line, and the file the
    recorder had finished is not put in place, since a failed run's outputs are not kept: the output
    folder the run created is gone again."""
    (tmp_path / "blocked").mkdir()
    pipeline = tmp_path / "full.yaml"
    pipeline.write_text(f"""\
name: full
operators:
  tick:   {{uses: toyops.Ticker, params: {{rate_hz: 1000, count: 20}}}}
  record: {{uses: recorder, inputs: {{imu: tick/imu}}, params: {{out: out}}}}
  sink:   {{uses: toyops.Unwritable, inputs: {{imu: tick/imu}}, params: {{path: "{tmp_path / "blocked"}"}}}}
""")
    proc = run_rover("run", str(pipeline), cwd=tmp_path, timeout=60)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.splitlines() == [
        f"rover: error: operator 'sink': {tmp_path / 'blocked'}: cannot write: Is a directory"
    ]
    assert not (tmp_path / "out").exists()


def test_a_second_signal_changes_nothing(tmp_path):
    """Ctrl-C, then SIGTERM while the outputs are being finished: still stopped by the first."""
    pipeline = tmp_path / "live.yaml"
    pipeline.write_text(LIVE)
    port = free_port()
    proc = popen_rover(
        "run", str(pipeline), "--host", "robot", "--output", str(tmp_path / "out"), "--set", f"port={port}"
    )
    with client(port) as watcher:
        _sub, flowing = data_event(watcher, "rover/live/pass/imu", 5)
        assert wait_for(flowing, proc), proc.communicate()
    proc.send_signal(signal.SIGINT)
    proc.send_signal(signal.SIGTERM)
    _out, err = proc.communicate(timeout=10)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert len(read_bag(tmp_path / "out" / "results.mcap")) >= 5


def test_a_run_ends_by_itself_at_end_of_stream(tmp_path):
    pipeline = tmp_path / "live.yaml"
    pipeline.write_text(LIVE)
    proc = run_rover("run", str(pipeline), "--output", str(tmp_path / "out"), "--set", "count=25", timeout=30)
    assert proc.returncode == 0, proc.stderr
    assert len(read_bag(tmp_path / "out" / "results.mcap")) == 25


def test_what_an_operator_drops_is_reported_at_the_end_of_the_run(tmp_path):
    pipeline = tmp_path / "thin.yaml"
    pipeline.write_text("""\
name: thin
operators:
  tick:   {uses: toyops.Ticker, params: {rate_hz: 1000, count: 9}}
  thin:   {uses: toyops.Thin, inputs: {imu: tick/imu}}
  record: {uses: recorder, inputs: {imu: thin/imu}, params: {out: out}}
""")
    proc = run_rover("run", str(pipeline), cwd=tmp_path, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "rover: WARNING: operator 'thin': dropped 4 messages of even rank\n" in proc.stderr
    assert len(read_bag(tmp_path / "out" / "results.mcap")) == 5


def recorded_without_drops(tmp_path, pipeline_text: str, timeout_s: int) -> list:
    """Run a pipeline whose recorder writes `out`: it must end well with nothing dropped; what it recorded."""
    pipeline = tmp_path / "pipeline.yaml"
    pipeline.write_text(pipeline_text)
    proc = run_rover("run", str(pipeline), cwd=tmp_path, timeout=timeout_s)
    assert proc.returncode == 0 and "dropped" not in proc.stderr, proc.stderr
    return read_bag(tmp_path / "out" / "results.mcap")


def test_what_a_host_built_is_kept_out_of_the_collectors_passes_while_it_runs(tmp_path):
    """A full pass over a host's modules and operators took 74-167 ms mid-run: longer than a dwell."""
    recorded = recorded_without_drops(
        tmp_path,
        """\
name: frozen
operators:
  tick:   {uses: toyops.Ticker, params: {rate_hz: 1000, count: 9}}
  check:  {uses: toyops.FrozenCheck, inputs: {imu: tick/imu}}
  record: {uses: recorder, inputs: {imu: check/imu}, params: {out: out}}
""",
        60,
    )
    assert len(recorded) == 9


def test_an_operator_does_its_work_ahead_while_no_input_waits(tmp_path):
    """The SLAM computes its tag search's steps ahead while it waits for an input: the runtime calls
    `on_idle` for as long as the operator has such work (`has_idle_work`) and none waits (the
    ticker sends its next message only once the work is done: in 10 s, or it counts a drop)."""
    recorded = recorded_without_drops(
        tmp_path,
        """\
name: ahead
workers: 1
operators:
  tick:   {uses: toyops.GatedTicker, params: {rate_hz: 1000, count: 5}}
  ahead:  {uses: toyops.AheadWork, inputs: {imu: tick/imu}}
  record: {uses: recorder, inputs: {imu: ahead/imu}, params: {out: out}}
""",
        120,
    )
    assert len(recorded) == 5


def test_the_profile_says_where_each_operators_time_went(tmp_path):
    """A sink that sleeps 20 ms per message shows it as handler time, the replay's sends wait on its
    full inbox, and a sink that takes 0.1 s to close shows that as its close."""
    dataset = write_imu_dataset(tmp_path / "short.mcap", 20)
    pipeline = tmp_path / "slow.yaml"
    pipeline.write_text(f"""\
name: slow
operators:
  replay: {{uses: dataset_replay, params: {{path: "{dataset}"}}}}
  slow:   {{uses: toyops.Slow, inputs: {{imu: replay/imu}}, params: {{delay_s: 0.02}}, inbox: 2}}
  probe:  {{uses: toyops.ProfileProbe, inputs: {{imu: replay/imu}}, params: {{path: profile.json, close_s: 0.1}}}}
""")
    proc = run_rover("run", str(pipeline), cwd=tmp_path, timeout=60)
    assert proc.returncode == 0, proc.stderr
    profile = json.loads((tmp_path / "profile.json").read_text())
    assert sorted(profile) == ["probe", "replay", "slow"]
    slow, replay, probe = profile["slow"], profile["replay"], profile["probe"]
    assert 0.4 <= slow["handler_s"] < 1.0, slow
    assert slow["decode_s"] > 0 and replay["encode_s"] > 0 and replay["handler_s"] > 0, (slow, replay)
    assert replay["send_s"] >= 0.2, replay  # 20 messages into an inbox of 2 drained at 50 Hz
    assert probe["handler_s"] < 0.1 and probe["idle_s"] > 0.2, probe
    assert probe["close_s"] >= 0.1 and slow["close_s"] < 0.05, (probe, slow)
    assert 0 < slow["cpu_s"] < 0.2, slow  # sleeping is not computing
    for name, parts in profile.items():
        assert all(v >= 0 for v in parts.values()), (name, parts)


def edit_pipeline(tmp_path: Path, dataset: Path, scale: str, *more: str) -> Path:
    """A pipeline in which `scale` (an operator editing its input) and `same` (a passthrough) take
    the same replayed IMU messages in one process, with `more` operators' lines after them."""
    pipeline = tmp_path / "edit.yaml"
    lines = [
        f'replay: {{uses: dataset_replay, params: {{path: "{dataset}"}}}}',
        f"scale: {{uses: {scale}, inputs: {{imu: replay/imu}}, params: {{gain: 2.0}}}}",
        "same: {uses: toyops.Passthrough, inputs: {imu: replay/imu}}",
        *more,
    ]
    pipeline.write_text("name: edit\noperators:\n" + "".join(f"  {line}\n" for line in lines))
    return pipeline


def test_an_operator_editing_its_input_changes_no_other_operators_input(tmp_path):
    """`scale` multiplies each message it receives in place (the README's example, a writable port)
    while `same` forwards the very same messages untouched, in one process: what `same` sent is the
    dataset's bytes, what `scale` sent is scaled. Messages are decoded once per process, yet no edit
    leaks."""
    dataset = write_imu_dataset(tmp_path / "imu.mcap", 200)
    record = "record: {uses: recorder, inputs: {scaled: scale/imu, same: same/imu}, params: {out: out}}"
    proc = run_rover("run", str(edit_pipeline(tmp_path, dataset, "toyops.Scale", record)), cwd=tmp_path, timeout=60)
    assert proc.returncode == 0, proc.stderr
    original = [data for topic, _t, data in read_bag(dataset) if topic == "/imu/data"]
    recorded = read_bag(tmp_path / "out" / "results.mcap")
    same = [data for topic, _t, data in recorded if topic.endswith("same")]
    scaled = [deserialize(data, "sensor_msgs/msg/Imu") for topic, _t, data in recorded if topic.endswith("scaled")]
    assert len(original) == 200 and same == original
    z = [deserialize(data, "sensor_msgs/msg/Imu").angular_velocity.z for data in original]
    assert [m.angular_velocity.z for m in scaled] == [2.0 * v for v in z]


def test_an_operator_editing_a_shared_input_fails_in_one_line_naming_the_field(tmp_path):
    """Without `writable`, the edit meets the message the process shares: the run fails, saying
    which operator, which field and what to do, and `same`'s input was never touched."""
    dataset = write_imu_dataset(tmp_path / "imu.mcap", 20)
    proc = run_rover("run", str(edit_pipeline(tmp_path, dataset, "toyops.ScaleShared")), cwd=tmp_path, timeout=60)
    assert proc.returncode == 1, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if "error" in line]
    assert len(errors) == 1, proc.stderr
    assert "operator 'scale'" in errors[0] and "geometry_msgs/msg/Vector3.z" in errors[0], errors
    assert "writable=True" in errors[0] and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_garbage_on_an_input_key_is_counted_and_the_pipeline_keeps_running(tmp_path):
    pipeline = tmp_path / "live.yaml"
    pipeline.write_text(LIVE)
    port = free_port()
    proc = popen_rover(
        "-v",
        "run",
        str(pipeline),
        "--host",
        "robot",
        "--output",
        str(tmp_path / "out"),
        "--set",
        "count=150",
        "--set",
        f"port={port}",
    )
    with client(port) as foreign:
        _token, ready = ready_event(foreign, "live", "robot")
        assert wait_for(ready, proc), proc.communicate()
        key = "rover/live/tick/imu"
        good = serialize(make("sensor_msgs/msg/Imu", header=header(0)))
        block = zenoh.CongestionControl.BLOCK
        for _ in range(5):
            foreign.put(key, b"\x00garbage\xff" * 7, congestion_control=block)
            foreign.put(
                key,
                b"\x00\x01\x00\x00" + b"\xff" * 3,
                encoding=codec.encoding("sensor_msgs/msg/Imu"),
                attachment=codec.attachment(codec.Kind.DATA, 0, 0),
                congestion_control=block,
            )
            foreign.put(
                key,
                good,
                encoding=codec.encoding("std_msgs/msg/String"),
                attachment=codec.attachment(codec.Kind.DATA, 0, 0),
                congestion_control=block,
            )
            # A valid message of another type for the recorder, whose inputs take any type: the
            # wire says pass/imu is sensor_msgs/msg/Imu, so it never reaches the recorder.
            foreign.put(
                "rover/live/pass/imu",
                serialize(make("std_msgs/msg/String", data="not an IMU")),
                encoding=codec.encoding("std_msgs/msg/String"),
                attachment=codec.attachment(codec.Kind.DATA, 0, 0),
                congestion_control=block,
            )
        _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert len(read_bag(tmp_path / "out" / "results.mcap")) == 150
    assert "imu:missing or malformed Rover attachment=5" in err
    assert "imu:bytes that do not decode as sensor_msgs/msg/Imu=5" in err
    assert "imu:type std_msgs/msg/String where sensor_msgs/msg/Imu was expected=5" in err
    record = next(line for line in err.splitlines() if "record: in" in line)
    assert "imu:type std_msgs/msg/String where sensor_msgs/msg/Imu was expected=5" in record


def test_a_failing_operator_is_one_line_and_status_1(tmp_path, dataset):
    pipeline = tmp_path / "boom.yaml"
    pipeline.write_text(f"""\
name: boom
operators:
  replay: {{uses: dataset_replay, params: {{path: "{dataset}"}}}}
  boom:   {{uses: toyops.Explode, inputs: {{imu: replay/imu}}}}
  record: {{uses: recorder, inputs: {{imu: boom/imu}}, params: {{out: "{tmp_path / "out"}"}}}}
""")
    proc = run_rover("run", str(pipeline), timeout=60)
    assert proc.returncode == 1
    assert "operator 'boom' (toyops.Explode) failed: ZeroDivisionError: boom (-v prints its traceback)" in proc.stderr
    assert "Traceback" not in proc.stderr
    verbose = run_rover("-v", "run", str(pipeline), timeout=60)
    assert verbose.returncode == 1
    assert "Traceback" in verbose.stderr and re.search(r'toyops\.py", line \d+, in on_input', verbose.stderr)
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir()), "a failed run left output"


def test_an_operator_failing_in_its_constructor_is_one_line_and_status_1(tmp_path, dataset):
    pipeline = tmp_path / "nodev.yaml"
    pipeline.write_text(f"""\
name: nodev
operators:
  replay: {{uses: dataset_replay, params: {{path: "{dataset}"}}}}
  imu:    {{uses: toyops.NoDevice, inputs: {{imu: replay/imu}}}}
""")
    proc = run_rover("run", str(pipeline), timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == [
        "rover: error: operator 'imu' (toyops.NoDevice) failed to start: FileNotFoundError: /dev/ttyUSB0"
    ]


def test_bad_inputs_are_one_line_and_status_2(tmp_path, dataset):
    pipeline = tmp_path / "toy.yaml"
    pipeline.write_text(TOY)
    missing = run_rover("run", str(pipeline), "--dataset", str(tmp_path / "nope.mcap"), cwd=tmp_path)
    assert missing.returncode == 2 and "nope.mcap: no such dataset file" in missing.stderr
    nothing = run_rover("run", "--output", str(tmp_path / "o"), cwd=tmp_path)
    assert nothing.returncode == 2 and "no dataset given" in nothing.stderr
    port = free_port()
    impatient = tmp_path / "impatient.yaml"
    impatient.write_text(
        TOY.replace(
            'b: {connect: ["tcp/127.0.0.1:${port}"]}', 'b: {connect: ["tcp/127.0.0.1:${port}"], wait_timeout_s: 1.5}'
        )
    )
    unreachable = run_rover(
        "run",
        str(impatient),
        "--host",
        "b",
        "--dataset",
        str(dataset),
        "--set",
        f"port={port}",
        timeout=60,
        cwd=tmp_path,
    )
    impatient.unlink()
    assert unreachable.returncode == 2
    assert "gave up after 1.5 s (wait_timeout_s) waiting for host(s) a, c" in unreachable.stderr
    assert f"b connects to tcp/127.0.0.1:{port}" in unreachable.stderr
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        in_use = run_rover(
            "run", str(pipeline), "--host", "a", "--dataset", str(dataset), "--set", f"port={taken}", cwd=tmp_path
        )
    assert in_use.returncode == 2 and f"cannot listen on tcp/127.0.0.1:{taken}" in in_use.stderr
    for proc in (missing, nothing, unreachable, in_use):
        assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["toy.yaml"], "a failed start left files behind"


def test_the_default_pipeline_runs_from_any_directory(tmp_path, dataset):
    proc = run_rover("run", "--dataset", str(dataset), "--output", "res", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert read_bag(tmp_path / "res" / "results.mcap") == [], "an IMU-only dataset gives no AoA and no epochs"


def test_watermarks_keep_a_live_run_flowing_past_a_silent_input(tmp_path):
    port = free_port()
    pipeline = tmp_path / "silent.yaml"
    pipeline.write_text(f"""\
name: silent
hosts:
  robot: {{listen: ["tcp/127.0.0.1:{port}"]}}
operators:
  tick:  {{uses: toyops.Ticker, host: robot, params: {{rate_hz: 50}}}}
  merge: {{uses: toyops.Merge, host: robot, inputs: {{a: tick/imu, b: tick/silent}}}}
""")
    proc = popen_rover("run", str(pipeline), "--host", "robot")
    try:
        with client(port) as watcher:
            _sub, enough = data_event(watcher, "rover/silent/merge/out", 50)
            flowing = wait_for(enough, proc)
    finally:
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=10)
    assert proc.returncode == 130, err
    assert flowing, f"fewer than 50 messages flowed in {WAIT_S:g} s while input 'b' was silent"


MESH = """\
name: mesh
vars: {dataset: "", output: out, port: 7447, port2: 7448}
hosts:
  nuc:    {listen: ["tcp/127.0.0.1:${port}"]}
  base:   {listen: ["tcp/127.0.0.1:${port2}"], connect: ["tcp/127.0.0.1:${port}"]}
  laptop: {connect: ["tcp/127.0.0.1:${port}", "tcp/127.0.0.1:${port2}"]}
operators:
  tick:    {uses: toyops.Ticker, host: nuc, params: {rate_hz: 50}}
  replay:  {uses: dataset_replay, host: base, params: {path: "${dataset}", speed: 4}}
  heading: {uses: toyops.Heading, host: laptop, inputs: {imu: replay/imu, odom: replay/odom}}
  record:  {uses: recorder, host: laptop, inputs: {pose: heading/pose, tick: tick/imu}, params: {out: "${output}"}}
"""


HOST_NAMES = ("nuc", "base", "laptop")


@pytest.mark.slow
def test_with_a_direct_link_losing_the_nuc_does_not_cut_base_from_the_laptop(tmp_path, dataset):
    """Base listens too and the laptop connects to both: kill -9 of the NUC mid-run leaves base's
    stream to the laptop whole (every pose), and both report the NUC lost, not as a hub (exit 3)."""
    pipeline = tmp_path / "mesh.yaml"
    pipeline.write_text(MESH)
    port, port2 = free_port(), free_port()
    sets = ["--set", f"port={port}", "--set", f"port2={port2}", "--dataset", str(dataset)]
    out = tmp_path / "out"
    procs = {h: popen_rover("run", str(pipeline), "--host", h, "--output", str(out), *sets) for h in HOST_NAMES}
    with client(port2) as watcher:
        _sub, started = data_event(watcher, "rover/mesh/heading/pose", 20)
        assert wait_for(started, procs["laptop"]), procs["laptop"].communicate()
    procs["nuc"].kill()
    results = {h: (p.communicate(timeout=WAIT_S)[1], p.returncode) for h, p in procs.items()}
    for host in ("base", "laptop"):
        err, rc = results[host]
        assert rc == 3, err
        assert "host nuc was lost" in err and "hub" not in err, err
    poses = [m for m in read_bag(out / "results.mcap") if m[0] == "/pose"]
    assert len(poses) == 400, f"{len(poses)} of 400 poses reached the laptop"


def test_a_promise_goes_out_as_soon_as_the_operator_is_idle(tmp_path):
    """An operator holding its latest input (as the AoA holds a burst until the next dwell's frames)
    promises what it holds (`held_since_ns`), and that promise goes out once it has nothing more to
    handle, not with its next message: the merge downstream sends each tick before the source's next
    one. The ticks are 10 ms apart in event time (no heartbeat, which waits for 100 ms of it) and
    0.5 s apart on the wall clock: without the idle promise each tick waits for the next."""
    port = free_port()
    pipeline = tmp_path / "held.yaml"
    pipeline.write_text(f"""\
name: held
hosts:
  robot: {{listen: ["tcp/127.0.0.1:{port}"]}}
operators:
  tick:  {{uses: toyops.Ticker, host: robot, params: {{rate_hz: 2, stamp_step_s: 0.01, count: 8, delay_s: 1}}}}
  pairs: {{uses: toyops.Pairs, host: robot, inputs: {{imu: tick/imu}}}}
  merge: {{uses: toyops.Merge, host: robot, inputs: {{a: tick/imu, b: pairs/out}}}}
""")
    arrivals: list[tuple[str, int]] = []
    lock = threading.Lock()

    def seen(sample: zenoh.Sample) -> None:
        att = sample.attachment
        kind, stamp, _mark = codec.read_attachment(att.to_bytes() if att is not None else None)
        if kind == codec.Kind.DATA:
            with lock:
                arrivals.append((str(sample.key_expr), stamp))

    proc = popen_rover("run", str(pipeline), "--host", "robot")
    with client(port) as watcher:
        subscribers = [watcher.declare_subscriber(f"rover/held/{key}", seen) for key in ("tick/imu", "merge/out")]
        _out, err = proc.communicate(timeout=60)
        for subscriber in subscribers:
            subscriber.undeclare()
    assert proc.returncode == 0, err
    ticks = [stamp for key, stamp in arrivals if key == "rover/held/tick/imu"]
    assert len(ticks) >= 4, f"the watcher saw {len(ticks)} ticks"
    for stamp, after in zip(ticks, ticks[1:], strict=False):
        merged = ("rover/held/merge/out", stamp)
        assert merged in arrivals and arrivals.index(merged) < arrivals.index(("rover/held/tick/imu", after)), (
            f"the tick stamped {stamp} left the merge only after the next tick: {arrivals}"
        )
