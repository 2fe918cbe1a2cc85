"""The forked math worker: results in order, errors raised again, a dead worker a clear error;
a calibrator that hands blocks to it reduces exactly the same windows as one that does not."""

from __future__ import annotations

import os
import signal
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA

from imucal_cli import api
from imucal_cli.api import estimate, stream_log
from imucal_cli.config import load_config
from imucal_cli.core.signals import TooLittleData
from imucal_cli.parallel import ForkedWorker

pytestmark = pytest.mark.skipif(not ForkedWorker.available(), reason="needs fork")

SAMPLE = DATA.parent.parent / "sample_data" / "urban.mcap"
CONFIG = DATA.parent.parent / "configs" / "sample_urban.yaml"


def _fail(message: str) -> None:
    raise TooLittleData(message)


def test_results_come_back_in_order_and_errors_are_raised_again():
    with ForkedWorker() as worker:
        pending = [worker.submit(np.sum, np.arange(n)) for n in range(1, 6)]
        failing = worker.submit(_fail, "too little data: 2 samples")
        after = worker.submit(os.getpid)
        assert [p.result() for p in pending] == [n * (n - 1) // 2 for n in range(1, 6)]
        with pytest.raises(TooLittleData, match="2 samples"):
            failing.result()
        assert after.result() != os.getpid()  # it ran in the other process
        assert after.done()


def test_jobs_and_results_larger_than_the_pipe_do_not_block_each_other():
    """Two jobs sent back to back, jobs and results far larger than a pipe holds: the second
    send waits for the first result instead of both processes waiting on each other."""
    import faulthandler

    faulthandler.dump_traceback_later(120, exit=True)  # a deadlock ends the run, not hangs it
    try:
        big = np.ones(4_000_000)  # 32 MB each way
        with ForkedWorker() as worker:
            first = worker.submit(np.multiply, big, 1.0)
            second = worker.submit(np.multiply, big, 2.0)
            assert first.done()  # collected before the second was sent
            assert second.result().sum() == 8_000_000.0 and first.result().sum() == 4_000_000.0
    finally:
        faulthandler.cancel_dump_traceback_later()


def test_a_worker_that_dies_is_a_clear_error():
    with ForkedWorker() as worker:
        pid = worker.submit(os.getpid).result()
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(RuntimeError, match="math worker process ended unexpectedly"):
            worker.submit(os.getpid).result()


def _windows(calibrator):
    return {
        name: [(w.number, w.valid, w.samples, w.base.packed_gyro.tobytes(), w.base.packed_accel.tobytes(), w.rows_gyro.tobytes(), w.rows_accel.tobytes()) for w in windows]
        for name, windows in calibrator.windows.items()
    }


def _infos(windows):
    return [(w.info.selected, w.info.rotation_std_deg, w.info.translation_std_m.tobytes()) for w in windows]


def test_blocks_reduced_by_the_worker_are_the_blocks_reduced_here(monkeypatch):
    config = load_config(CONFIG)
    inline = stream_log(SAMPLE, config, background=False).calibrator
    assert inline.executor is None
    workers = []

    class Recorded(ForkedWorker):
        def __init__(self) -> None:
            super().__init__()
            workers.append(self)

    monkeypatch.setattr(api, "ForkedWorker", Recorded)
    streamed = stream_log(SAMPLE, config)  # the reader and the math worker forked
    forked = streamed.calibrator
    assert len(workers) == 1 and forked.executor is None  # let go once the log is read
    assert not workers[0]._process.is_alive()
    assert sum(len(w) for w in inline.windows.values()) > 20
    assert _windows(forked) == _windows(inline)  # bit for bit, in window order
    result = estimate(streamed)
    expected = inline.estimates()
    for name, sensor in expected.items():
        assert np.array_equal(result.estimates[name].T_base_imu.translation, sensor.T_base_imu.translation)
        assert np.array_equal(result.estimates[name].covariance, sensor.covariance)
        assert _infos(forked.windows[name]) == _infos(inline.windows[name])


def test_a_concurrent_futures_executor_will_do_and_the_estimates_are_identical():
    from imucal_cli.io.logs import ImuBatches
    from imucal_cli.pipeline import make_calibrator

    config = load_config(CONFIG)
    inline = stream_log(SAMPLE, config, background=False).calibrator
    names = {config.base.topic: "base"} | {s.imu_topic: s.name for s in config.sensors}
    calibrator = make_calibrator(config)
    with ThreadPoolExecutor(1) as pool:
        calibrator.executor = pool
        for topic, stamps, _, gyro, accel in ImuBatches(SAMPLE, names):
            calibrator.add(names[topic], stamps, gyro, accel)
        calibrator.process(final=True)
        got = calibrator.estimates()
    assert _windows(calibrator) == _windows(inline)
    expected = inline.estimates()
    assert set(got) == set(expected)
    for name, sensor in expected.items():
        assert np.array_equal(got[name].T_base_imu.translation, sensor.T_base_imu.translation)
        assert np.array_equal(got[name].T_base_imu.rotation.as_quat(), sensor.T_base_imu.rotation.as_quat())


def test_a_reader_started_early_is_used_when_its_topics_are_the_configs_and_closed_otherwise():
    """The CLI starts the reader before the math's imports (``start_reading``): ``stream_log``
    takes it over when it reads the config's topics, and ends it and reads anew when not."""
    import multiprocessing

    from imucal_cli.io.logs import start_reading

    config = load_config(CONFIG)
    inline = stream_log(SAMPLE, config, background=False).calibrator
    topics = [config.base.topic, *(s.imu_topic for s in config.sensors)]
    early = start_reading(SAMPLE, topics)
    streamed = stream_log(SAMPLE, config, reading=early)
    assert streamed.calibrator.windows and _windows(streamed.calibrator) == _windows(inline)
    assert streamed.stats.keys() == set(topics)
    wrong = start_reading(SAMPLE, topics[:2])  # not the config's topics: ended, read anew
    streamed = stream_log(SAMPLE, config, reading=wrong)
    assert _windows(streamed.calibrator) == _windows(inline)
    assert not wrong[1]._process.is_alive()
    assert not multiprocessing.active_children()


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["calibrate", "d.mcap", "-c", "c.yaml"], ("d.mcap", "c.yaml")),
        (["segments", "-o", "out.json", "--config", "c.yaml", "--json", "d.mcap"], ("d.mcap", "c.yaml")),
        (["calibrate", "--report", "figs", "d.mcap", "--config=c.yaml", "--require-observable"], ("d.mcap", "c.yaml")),
        (["calibrate", "d.mcap"], None),  # no config: the CLI will say so
        (["calibrate", "d.mcap", "-c"], None),
        (["calibrate", "d.mcap", "-c", "c.yaml", "--help"], None),
        (["calibrate", "d.mcap", "other.mcap", "-c", "c.yaml"], None),  # a usage error
        (["biases", "d.mcap", "-c", "c.yaml"], None),  # reads the whole log its own way
        (["--version"], None),
        ([], None),
    ],
)
def test_the_entry_point_guesses_the_log_and_config_of_streaming_commands_only(args, expected):
    from imucal_cli import launch

    found = launch.log_and_config(args)
    assert found == (None if expected is None else tuple(Path(p) for p in expected))


def test_the_entry_point_starts_the_reader_before_the_cli_and_hands_it_over():
    """``imucal calibrate LOG -c CONFIG`` forks the log's reader before the CLI's imports; the
    CLI takes it over for that log and config (the same windows as reading inline), and a
    reading started for another log or config is ended, not used."""
    import multiprocessing

    from imucal_cli import launch

    config = load_config(CONFIG)
    inline = stream_log(SAMPLE, config, background=False).calibrator
    launch.begin(["calibrate", str(SAMPLE), "-c", str(CONFIG), "--json"])
    early = launch.take_early(SAMPLE, CONFIG)
    assert early is not None and launch.take_early(SAMPLE, CONFIG) is None  # taken once
    streamed = stream_log(SAMPLE, config, reading=early)
    assert streamed.calibrator.windows and _windows(streamed.calibrator) == _windows(inline)
    assert streamed.stats.keys() == {config.base.topic, *(s.imu_topic for s in config.sensors)}
    assert sum(s.messages for s in streamed.stats.values()) > 0 and streamed.format_name == "mcap"
    launch.begin(["segments", str(SAMPLE), "-c", str(CONFIG)])
    guessed = launch._early
    assert guessed is not None
    assert launch.take_early(SAMPLE, CONFIG.with_name("other.yaml")) is None
    assert not guessed[2][1]._process.is_alive()
    assert not multiprocessing.active_children()


def test_the_cli_ends_the_early_reader_when_the_config_is_bad(tmp_path, monkeypatch):
    """Topics read plainly, then the full check fails: one clear message, exit 2, no process
    left behind."""
    import multiprocessing

    import yaml
    from typer.testing import CliRunner

    from imucal_cli import launch
    from imucal_cli.cli import app

    started = []
    start_reading = launch.start_reading
    monkeypatch.setattr(launch, "start_reading", lambda *args: started.append(args) or start_reading(*args))

    document = yaml.safe_load(CONFIG.read_text())
    document["rest"] = {"no_such_key": 1}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(document))
    result = CliRunner().invoke(app, ["calibrate", str(SAMPLE), "-c", str(bad)])
    assert result.exit_code == 2
    assert "no_such_key" in result.output and "Traceback" not in result.output
    assert len(started) == 1  # the reader was started before the check
    assert not multiprocessing.active_children()


def test_children_end_when_the_parent_dies_mid_transfer(tmp_path):
    """A parent killed while its math worker and its log reader are blocked sending to it: they
    hold no copy of the parent's pipe ends (nor of each other's), so they see the pipe break and
    end instead of waiting for ever."""
    import subprocess
    import sys
    import time

    script = f"""
import os, sys, time
import numpy as np
from imucal_cli.io.logs import start_reading
from imucal_cli.parallel import ForkedWorker
reader, batches = start_reading({str(SAMPLE)!r}, ["/gnss/imu", "/lidar/front_left_top/imu"])
worker = ForkedWorker()
worker.submit(np.ones, 8_000_000)  # a 64 MB result the parent never reads
time.sleep(1.0)  # both children now blocked sending
open({str(tmp_path / "pids")!r}, "w").write(f"{{worker._process.pid}} {{batches._process.pid}}")
os._exit(0)
"""
    # no pipes to the script: its orphans would hold them open
    subprocess.run([sys.executable, "-c", script], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=120, check=True)
    pids = [int(p) for p in (tmp_path / "pids").read_text().split()]
    assert len(pids) == 2
    def running(pid: int) -> bool:  # not gone, and not a zombie waiting for its dead parent's reaper
        try:
            return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
        except OSError:
            return False

    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(running(p) for p in pids):
        time.sleep(0.1)
    alive = [p for p in pids if running(p)]
    for p in alive:
        os.kill(p, signal.SIGKILL)
    assert not alive


def _echo_child(conn_in, conn_out):
    from imucal_cli.parallel import receive, send

    while (item := receive(conn_in)) is not None:
        send(conn_out, item)
    conn_out.close()


def test_objects_cross_the_pipe_whole_their_arrays_bit_exact():
    """Arrays go as raw bytes beside the pickle: every layout, dtype and size (far past what a
    pipe holds) comes back equal, writable, in order; a closed pipe mid-object is EOFError."""
    import multiprocessing

    from imucal_cli.parallel import receive, send, widen

    context = multiprocessing.get_context("fork")
    to_child_r, to_child_w = context.Pipe(duplex=False)
    from_child_r, from_child_w = context.Pipe(duplex=False)
    widen(to_child_w)
    child = context.Process(target=_echo_child, args=(to_child_r, from_child_w), daemon=True)
    child.start()
    to_child_r.close()
    from_child_w.close()
    rng = np.random.default_rng(7)
    big = rng.standard_normal((1_500_000, 3))  # 36 MB: many times the pipe
    objects = [
        ("/imu", np.arange(5, dtype=np.int64), big, np.asfortranarray(big[:1000]), big[::7]),  # C, F, strided
        {"empty": np.zeros((0, 3)), "u8": rng.integers(0, 255, 33, dtype=np.uint8), "obj": np.array(["a", None], dtype=object)},
        [np.float32(1.5), 3, "text", None],
    ]
    for obj in objects:
        send(to_child_w, obj)
        back = receive(from_child_r)
        assert type(back) is type(obj)
        for a, b in zip(obj.values() if isinstance(obj, dict) else obj, back.values() if isinstance(back, dict) else back, strict=True):
            if isinstance(a, np.ndarray):
                assert a.dtype == b.dtype and a.shape == b.shape and (a.tobytes() == b.tobytes() if a.dtype != object else list(a) == list(b))
                b[...] = b  # writable
            else:
                assert a == b
    send(to_child_w, None)
    child.join(timeout=30)
    # the other end gone in the middle of an object: the header promised bytes that never come
    import pickle

    r, w = context.Pipe(duplex=False)
    w.send_bytes(pickle.dumps((b"", [100]), protocol=5))
    w.close()
    with pytest.raises(EOFError):
        receive(r)


def _slow_square(x):
    import time

    time.sleep(0.02 * (x % 3))  # later items often finish first
    if x == 7:
        raise ValueError("seven")
    return x * x


def test_ordered_map_keeps_order_raises_in_turn_and_stops_cleanly():
    import threading

    from imucal_cli.io.prefetch import ordered_map

    for workers in (0, 1, 3):
        got = []
        with pytest.raises(ValueError, match="seven"):
            for value in ordered_map(_slow_square, range(20), workers, 2):
                got.append(value)  # noqa: PERF402 - what came before the exception is kept
        assert got == [x * x for x in range(7)]  # all before the failing item, in order

    started = []

    def record(x):
        started.append(x)
        return x

    items = ordered_map(record, range(1000), 2, 2)
    assert [next(items) for _ in range(3)] == [0, 1, 2]
    items.close()  # nothing more is started, and what was started has ended
    assert len(started) <= 3 + 2 + 2
    assert not [t for t in threading.enumerate() if t.name.startswith("imucal-decode")]


def test_the_command_runs_one_blas_thread_a_process_unless_the_environment_says(tmp_path):
    """``calibrate``'s processes keep the cores busy themselves: the entry point sets OpenBLAS to
    one thread before numpy is imported, and leaves a count the environment gives alone."""
    import subprocess
    import sys

    probe = "import os, sys; from imucal_cli import launch; launch.begin(sys.argv[1:]); print(os.environ.get('OPENBLAS_NUM_THREADS'), os.environ.get('OMP_NUM_THREADS'))"
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")}
    plain = subprocess.run([sys.executable, "-c", probe, "inspect", "x.mcap"], env=env, capture_output=True, text=True, check=True)
    assert plain.stdout.split() == ["1", "None"]
    given = subprocess.run([sys.executable, "-c", probe, "inspect", "x.mcap"], env=env | {"OMP_NUM_THREADS": "4"}, capture_output=True, text=True, check=True)
    assert given.stdout.split() == ["None", "4"]
