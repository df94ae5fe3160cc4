"""Live at sensor rate: ``kentreg_node`` fed a recording at its real rate over loopback DDS.

The node started as a user starts it, a 10 Hz stream of raw scans (``kitti_hdl64``: the HDL-64E
street frames; ``balm_10hz``: the BALM scans at five times their rate) published without
waiting for it over Fast DDS (the shipped shared-memory profile, or loopback UDP). Per run
(:func:`measure_live`): drops, publish-to-odometry latency, CPU per core and of the node; beside
it the sequential loop's stages and sequential against pipelined
throughput (:func:`measure_throughput`) and ``per_scan.py``'s table from the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Sequence
from itertools import product
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository, for benchmarks.*

from benchmarks.harness import datasets, report, runner  # noqa: E402
from benchmarks.harness.report import git_describe, machine_info  # noqa: E402

FloatArray = NDArray[np.float64]
Scans = Sequence[NDArray[Any]]

#: The shipped profile: shared memory plus UDP on 127.0.0.1.
SHM_PROFILE = ROOT / 'config' / 'fastdds_shm.xml'
#: UDP on loopback only (the tests' profile before shared memory): large clouds get lost.
UDP_PROFILE = ROOT / 'benchmarks' / 'fastdds_udp.xml'
#: Seconds the node gets after start-up before the stream (its worker process imports and
#: loads the compiled kernels; a sensor does not wait for it, but a user starts the node first).
SETTLE_S = 4.0
#: Seconds after the last scan to wait for its odometry.
DRAIN_S = 3.0
#: The streams (10 Hz) and the data sets they replay.
STREAMS = {'kitti_hdl64': 'kitti_raw_hdl64', 'balm_10hz': 'balm'}
#: The node's diagnostics totals each run records.
DIAGNOSTIC_TOTALS = ('received', 'published', 'dropped_queue', 'errors', 'fell_back')


def load_stream(name: str, n: int) -> tuple[list[NDArray[np.float32]], list[int], float]:
    """The first ``n`` scans of a stream as float32 (N, 3), their stamps (ns) and its rate."""
    sequence = datasets.load_dataset(STREAMS[name])
    scans = [np.asarray(s.points, dtype=np.float32) for s in sequence.scans[:n]]
    stamps = [1_700_000_000 * 10**9 + int(i * 1e9 / 10.0) for i in range(len(scans))]
    return scans, stamps, 10.0


def _node_env(profile: str) -> dict[str, str]:
    env = dict(os.environ) | {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    path = SHM_PROFILE if profile == 'shm' else UDP_PROFILE
    env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(path)
    env.setdefault('ROS_DOMAIN_ID', os.environ.get('KENTREG_TEST_ROS_DOMAIN_ID', '77'))
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(ROOT), env.get('PYTHONPATH')) if p)
    return env


def measure_live(
    scans: Scans, stamps: Sequence[int], *, rate_hz: float, model: str, pipeline: str,
    profile: str = 'shm',
) -> dict[str, Any]:  # fmt: skip
    """Publish ``scans`` at ``rate_hz`` to a ``kentreg_node`` subprocess; what came back.

    The benchmark process must run with the DDS environment of ``profile`` (see :func:`main`,
    which runs each measurement in a child process with it).
    """
    import rclpy
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry as OdometryMsg
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header

    from kentreg_ros.io import names
    from kentreg_ros.io.pointcloud2 import array_to_pointcloud2, rclpy_factory

    ns, log = f'/live_{uuid.uuid4().hex[:8]}', tempfile.TemporaryFile()
    cmd = _node_command(ns, names.DIAGNOSTICS, model, pipeline)
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ))
    rclpy.init()
    node = rclpy.create_node(f'live_bench_{ns[6:]}')
    received: dict[int, float] = {}
    diagnostics: list[dict[str, str]] = []

    def on_odom(msg: Any) -> None:
        stamp = msg.header.stamp
        received.setdefault(stamp.sec * 10**9 + stamp.nanosec, time.monotonic())

    def on_diag(msg: Any) -> None:
        diagnostics.extend({kv.key: kv.value for kv in s.values} for s in msg.status)

    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        factory = rclpy_factory(PointCloud2, PointField, Header, Time)
        messages = [array_to_pointcloud2(p, frame_id='lidar', stamp_ns=s, factory=factory)
                    for p, s in zip(scans, stamps, strict=True)]  # fmt: skip
        pub = node.create_publisher(PointCloud2, f'{ns}/{names.POINTS}', qos_profile_sensor_data)
        odom_topic = f'{ns}/{names.ODOMETRY}'
        node.create_subscription(OdometryMsg, odom_topic, on_odom, 50)
        node.create_subscription(DiagnosticArray, f'{ns}/diagnostics', on_diag, 50)
        deadline = time.monotonic() + 60.0
        while pub.get_subscription_count() == 0 or node.count_publishers(odom_topic) == 0:
            if time.monotonic() > deadline or proc.poll() is not None:
                log.seek(0)
                text = log.read().decode(errors='replace')[-3000:]
                raise RuntimeError(f'kentreg_node did not come up:\n{text}')
            time.sleep(0.05)
        time.sleep(SETTLE_S)
        cpu0, node0, t0 = runner.cpu_times(), runner.tree_cpu_s(proc.pid), time.monotonic()
        sent: dict[int, float] = {}
        for i, (msg, stamp) in enumerate(zip(messages, stamps, strict=True)):
            _spin_until(executor, t0 + i / rate_hz)
            sent[stamp] = time.monotonic()
            pub.publish(msg)
        stream_s = time.monotonic() - t0
        cpu1, node1 = runner.cpu_times(), runner.tree_cpu_s(proc.pid)
        _spin_until(executor, time.monotonic() + DRAIN_S)
    finally:
        _stop_node(proc)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    by_scan = [round(1e3 * (received[s] - sent[s]), 1) if s in received else None for s in stamps]
    latency = np.array([1e3 * (received[s] - sent[s]) for s in sent if s in received])
    cores = [round(100.0 * (b1 - b0) / max(t1 - t0_, 1), 1)
             for (b0, t0_), (b1, t1) in zip(cpu0, cpu1, strict=True)]  # fmt: skip
    last = diagnostics[-1] if diagnostics else {}
    quantiles = [round(float(np.percentile(latency, q)), 1) if len(latency) else float('nan')
                 for q in (50, 95, 100)]  # fmt: skip
    return {
        'model': model, 'pipeline': pipeline, 'dds': profile, 'rate_hz': rate_hz,
        'published': len(sent), 'processed': len(latency), 'dropped': len(sent) - len(latency),
        'dropped_pct': round(100.0 * (len(sent) - len(latency)) / max(len(sent), 1), 1),
        'latency_ms': dict(zip(('p50', 'p95', 'max'), quantiles, strict=True)),
        'node_diagnostics': {f'total.{k}': last.get(f'total.{k}', '') for k in DIAGNOSTIC_TOTALS},
        'node_latency_ms_mean_max': [(d.get('latency_ms_mean'), d.get('latency_ms_max'))
                                     for d in diagnostics],
        'cpu_pct_per_core': cores, 'node_cpu_pct': round(100.0 * (node1 - node0) / stream_s, 1),
        'exit_code': proc.returncode,
        'missing': [i for i, s in enumerate(stamps) if s not in received],
        'latency_by_scan_ms': by_scan,
    }  # fmt: skip


def _node_command(ns: str, diagnostics: str, model: str, pipeline: str) -> list[str]:
    """``kentreg_node`` in namespace ``ns`` with the model and pipeline under test (and the
    ``name:=value`` parameters of ``KENTREG_LIVE_PARAMS``, space-separated, for a variant)."""
    remap = ['-r', f'__ns:={ns}', '-r', f'{diagnostics}:={ns}/diagnostics']
    params = [f'model:={model}', f'pipeline:={pipeline}', 'diagnostics_period:=1.0',
              *os.environ.get('KENTREG_LIVE_PARAMS', '').split()]  # fmt: skip
    node = [sys.executable, '-m', 'kentreg_ros.ros.node', '--ros-args', *remap]
    return node + [arg for p in params for arg in ('-p', p)]


def _spin_until(executor: Any, deadline: float) -> None:
    """Take the odometry in this thread until ``deadline`` (an executor shut down under a thread
    still spinning it once kept the GIL in that thread and hung the run, one in 25)."""
    while (left := deadline - time.monotonic()) > 0.0:
        executor.spin_once(timeout_sec=left)


def _stop_node(proc: subprocess.Popen[bytes]) -> None:
    """Ctrl-C, as a user stops it; killed after 20 s."""
    proc.send_signal(2)
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _timed_step(odometry: Any, points: Any, stamp: int, rows: dict[str, list[float]]) -> Any:
    """One sequential step; its stage times (ms: prepare, register, model upkeep, total wall and
    CPU time, what it costs whatever shares the core) appended to ``rows``, the first scan's
    (prepare only) left out. Returns the pose."""
    t0, c0 = time.perf_counter(), time.process_time()
    step = odometry.step(points, stamp)
    wall, cpu = 1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)
    if step.index:
        pre, reg = step.timings.get('preprocess', 0.0), step.timings.get('register', 0.0)
        values = {'prepare': pre, 'register': reg, 'model': wall - pre - reg, 'total': wall,
                  'cpu': cpu} | {k: v for k, v in step.timings.items() if k in PARTS}  # fmt: skip
        for key, value in values.items():
            rows.setdefault(key, []).append(value)
    return step.T_world_lidar


def measure_throughput(
    scans: Scans, stamps: Sequence[int], *, model: str, rounds: int = 2
) -> dict[str, Any]:
    """Milliseconds per scan of the sequential and the pipelined loop, fed as fast as they take
    the scans (the next scan handed over before each step), in alternating rounds; and whether
    their poses are identical."""
    from kentreg_ros.core import KentRegConfig, Odometry
    from kentreg_ros.runtime import ProcessPreparer

    config = KentRegConfig().with_updates({'odometry.model': model})
    times: dict[str, list[float]] = {'sequential': [], 'pipelined': []}
    poses: dict[str, list[FloatArray]] = {}
    cpu: dict[str, list[float]] = {'sequential': [], 'main': [], 'worker': []}
    n = len(scans)
    stages: dict[str, list[float]] = {}
    for _ in range(rounds):
        sequential = Odometry(config)
        t0, c0 = time.perf_counter(), time.process_time()
        poses['sequential'] = [
            _timed_step(sequential, p, s, stages) for p, s in zip(scans, stamps, strict=True)
        ]
        times['sequential'].append(1e3 * (time.perf_counter() - t0) / n)
        cpu['sequential'].append(1e3 * (time.process_time() - c0) / n)
        with ProcessPreparer() as preparer:
            pipelined = Odometry(config, preparer=preparer)
            time.sleep(SETTLE_S)
            worker = preparer.worker_pid
            got = []
            t0, c0 = time.perf_counter(), time.process_time()
            w0 = runner.tree_cpu_s(worker) if worker else 0.0
            preparer.prefetch(scans[0], stamps[0])
            for i, (p, s) in enumerate(zip(scans, stamps, strict=True)):
                if i + 1 < len(scans):
                    preparer.prefetch(scans[i + 1], stamps[i + 1])
                got.append(pipelined.step(p, s).T_world_lidar)
            times['pipelined'].append(1e3 * (time.perf_counter() - t0) / n)
            cpu['main'].append(1e3 * (time.process_time() - c0) / n)
            w1 = runner.tree_cpu_s(worker) if worker else 0.0
            cpu['worker'].append(1e3 * (w1 - w0) / n)
            poses['pipelined'] = got
    seq, pipe = (float(np.median(times[k])) for k in ('sequential', 'pipelined'))
    compared = zip(poses['sequential'], poses['pipelined'], strict=True)
    identical = all(np.array_equal(a, b) for a, b in compared)
    # CPU per scan (all threads of the process; the worker's from /proc): what each core would
    # have to give, whatever else runs on the machine.
    quantiles = {k: round(float(np.median(v)), 1) for k, v in stages.items()}
    for key in ('total', 'cpu'):
        quantiles[f'{key}_p95'] = round(float(np.percentile(stages[key], 95)), 1)
    return {
        'stages': quantiles, 'sequential_ms': round(seq, 1), 'pipelined_ms': round(pipe, 1),
        'speedup': round(seq / pipe, 2), 'poses_identical': identical,
        'rounds_ms': {k: [round(v, 1) for v in vs] for k, vs in times.items()},
        **{f'{k}_cpu_ms': round(float(np.median(cpu[k])), 1) for k in cpu},
    }  # fmt: skip


def _in_child(
    kind: str, stream: str, n: int, kwargs: dict[str, Any], env: dict[str, str],
    niceness: int = 10,
) -> Any:  # fmt: skip
    """Run one measurement in a fresh process (its own DDS environment, no state carried)."""
    how = json.dumps(kwargs | {'nice': niceness})
    result = runner.in_subprocess(__file__, ['--child', kind, stream, str(n), how], env=env)
    if 'error' in result:
        raise RuntimeError(f'{kind} {stream} {kwargs} failed: {result["error"]}')
    return result


def run_child(args: argparse.Namespace) -> dict[str, Any]:
    """The measurement of ``--child KIND STREAM N JSON`` (in its own process, at its niceness)."""
    kind, stream, n, text = args.child
    kwargs = json.loads(text)
    os.nice(kwargs.pop('nice'))
    scans, stamps, rate = load_stream(stream, int(n))
    measure = measure_live if kind == 'live' else measure_throughput
    return measure(scans, stamps, **kwargs | ({'rate_hz': rate} if kind == 'live' else {}))


def run(options: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    """Every measurement of the options; the result document."""
    tmp = Path(tempfile.mkdtemp(prefix='kentreg_live_'))
    doc: dict[str, Any] = {'benchmark': 'live', 'commit': git_describe(),
                           'machine': machine_info(), 'scans': options.scans,
                           'live_niceness': options.live_nice, 'streams': {}}  # fmt: skip
    for stream in options.streams:
        entry: dict[str, Any] = {'live': [], 'stages': {}, 'throughput': {}}
        for model in options.models:  # back to back: their ratio is read from one phase
            print(f'live: {stream} {model} throughput (load {os.getloadavg()[0]:.2f})', flush=True)
            th = _in_child('throughput', stream, options.scans, {'model': model}, _node_env('shm'))
            entry['stages'][model], entry['throughput'][model] = th.pop('stages'), th
        for model in options.models:
            for dds, pipeline, r in product(options.dds, options.pipelines, range(options.rounds)):
                how = {'model': model, 'pipeline': pipeline, 'profile': dds}
                load = os.getloadavg()[0]
                res = _in_child('live', stream, options.scans, how, _node_env(dds),
                                options.live_nice)  # fmt: skip
                res |= {'round': r, 'load_before': round(load, 2),
                        'load_after': round(os.getloadavg()[0], 2)}  # fmt: skip
                entry['live'].append(res)
                print(f'live: {stream} {model} {pipeline} {dds}: dropped {res["dropped"]}, '
                      f'latency {res["latency_ms"]} ms', flush=True)  # fmt: skip
        doc['streams'][stream] = entry
    if options.per_scan:
        out = tmp / 'per_scan'
        print('live: per_scan.py kentreg gicp kiss_icp', flush=True)
        script = str(ROOT / 'benchmarks' / 'per_scan.py')
        rounds = ['--rounds', str(options.per_scan_rounds)]
        # The memory run (--long-steps) is per_scan.py's own business.
        cmd = [*('nice', sys.executable, script, '--methods', 'kentreg', 'gicp', 'kiss_icp'),
               *rounds, '--long-steps', '0', '--out', str(out)]  # fmt: skip
        subprocess.run(cmd, check=True)
        doc['per_scan'] = json.loads((out / 'per_scan.json').read_text())
        doc['per_scan_table'] = (out / 'per_scan.md').read_text()
    doc['load_end'] = [round(x, 2) for x in os.getloadavg()]
    return doc


#: The columns of the live table: a row per run.
LIVE: list[report.Column] = [
    ('stream', 'stream:s'), ('model', 'model:s'), ('pipeline', 'pipeline:s'), ('DDS', 'dds:s'),
    ('dropped', lambda r: f'{r["dropped"]}/{r["published"]} ({r["dropped_pct"]} %)'),
    ('latency p50 / p95 / max (ms)', lambda r: '{p50} / {p95} / {max}'.format(**r['latency_ms'])),
    ('cores busy (%)', lambda r: ' / '.join(str(c) for c in r['cpu_pct_per_core'])),
    ('node CPU (%)', 'node_cpu_pct:'), ('load', 'load_before:'),
]  # fmt: skip
#: The columns of the offline table: a row per stream and model (stages and throughput).
OFFLINE: list[report.Column] = [
    ('stream', 'stream:s'), ('model', 'model:s'), ('prepare', 'prepare:'),
    ('register', 'register:'), ('model upkeep', 'model_ms:'),
    ('total p50 / p95', lambda r: f'{r["total"]} / {r["total_p95"]}'),
    ('CPU p50 / p95', lambda r: f'{r["cpu"]} / {r["cpu_p95"]}'),
    ('sequential / pipelined fed at once (ms/scan)',
     lambda r: f'{r["th"]["sequential_ms"]} / {r["th"]["pipelined_ms"]}'),
    ('speed-up', lambda r: f'{r["th"]["speedup"]}x'), ('poses identical', 'th.poses_identical:'),
]  # fmt: skip
#: The parts of those stages (the step's timings), in the table under it.
PARTS = ['prepare.downsample', 'prepare.neighbours', 'prepare.normals', 'prepare.outliers',
         'prepare.clustering', 'rotation', 'translation', 'refine', 'model.map_insert',
         'model.map_frame', 'model.map_tree']  # fmt: skip
BREAKDOWN: list[report.Column] = [('stream', 'stream:s'), ('model', 'model:s'), *(
    (p.split('.')[-1].replace('_', ' '), lambda r, p=p: str(r.get(p, '–'))) for p in PARTS
)]  # fmt: skip


def _notes(stream: str, entry: dict[str, Any]) -> list[str]:
    """The sentences under the offline table: the local map's cost and the pipelined bound."""
    lines, st = [], entry['stages']
    if {'previous_scan', 'local_map'} <= set(st):
        wall = st['local_map']['total'] / st['previous_scan']['total']
        cpu = st['local_map']['cpu'] / st['previous_scan']['cpu']
        lines.append(
            f'- {stream}: local map / previous scan per scan (sequential, one thread): '
            f'{cpu:.2f}x in CPU time, {wall:.2f}x in wall time.'
        )
    for model, th in entry['throughput'].items():
        bound = max(th['main_cpu_ms'], th['worker_cpu_ms'], 1e-9)
        lines.append(
            f'- {stream}, {model}, fed at once: CPU per scan {th["sequential_cpu_ms"]} ms '
            f'sequential; pipelined {th["main_cpu_ms"]} ms in the main process and '
            f'{th["worker_cpu_ms"]} ms in the worker, so with two free cores one scan every '
            f'{bound:.1f} ms at best ({th["sequential_cpu_ms"] / bound:.2f}x).'
        )
    return lines


def render(doc: dict[str, Any]) -> str:
    """The Markdown report of a result document."""
    streams = doc['streams'].items()
    runs = [{'stream': s, **r} for s, e in streams for r in e['live']]
    offline = [{**st, 'stream': s, 'model': m, 'model_ms': st['model'], 'th': e['throughput'][m]}
               for s, e in streams for m, st in e['stages'].items()]  # fmt: skip
    lines = [
        '# Live at sensor rate',
        '',
        f'`benchmarks/live.py` at {doc["commit"]}: `kentreg_node` (its own process) fed each '
        'stream at 10 Hz by a publisher that does not wait for it, over Fast DDS on loopback '
        '(shm: `config/fastdds_shm.xml`, shared memory plus loopback UDP; udp: loopback UDP '
        f'only); {doc["scans"]} scans per run. Latency: from publishing a cloud to receiving '
        "its odometry (an upper bound of the node's receipt-to-publication latency). CPU: "
        'each core over the stream (the machine is shared: the load average is the 1-minute '
        "one before each run), and the node's processes (100 % = one core).",
        '',
        *report.column_table(LIVE, runs),
        '',
        '## Per scan on this machine (one thread; sequential loop stages, median ms)',
        '',
        *report.column_table(OFFLINE, offline),
        '',
        'Their parts (median ms; registration: rotation EM, translation, refinement, without '
        'the start-free search of doubtful steps; the local map: insertion, frame, KD-tree):',
        '',
        *report.column_table(BREAKDOWN, offline),
        '',
        *(line for stream, entry in streams for line in _notes(stream, entry)),
    ]
    if 'per_scan_table' in doc:
        head = '## Per raw scan against GICP and KISS-ICP (`benchmarks/per_scan.py`, same run)'
        lines += ['', head, '']
        lines += [ln for ln in doc['per_scan_table'].splitlines() if not ln.startswith('# ')]
    lines += ['', f'Load average at the end: {doc["load_end"]}.', '']
    return '\n'.join(lines)


OPTIONS: list[report.Option] = [
    ('--streams', {'nargs': '+', 'default': list(STREAMS), 'choices': list(STREAMS)}),
    ('--models', {'nargs': '+', 'default': ['previous_scan', 'local_map']}),
    ('--pipelines', {'nargs': '+', 'default': ['process', 'sequential']}),
    ('--dds', {'nargs': '+', 'default': ['shm'], 'choices': ['shm', 'udp']}),
    ('--scans', {'type': int, 'default': 50}),
    ('--rounds', {'type': int, 'default': 1}),
    ('--no-per-scan', {'dest': 'per_scan', 'action': 'store_false'}),
    ('--per-scan-rounds', {'type': int, 'default': 2}),
    ('--live-nice', {'type': int, 'default': 0, 'help': 'niceness of the live runs (node and '
                     'publisher; default 0, as a user runs them: on a shared machine, work at a '
                     'higher niceness then takes the leftover CPU); the offline measurements run '
                     'at 10'}),
    ('--child', {'nargs': 4, 'help': argparse.SUPPRESS}),  # one measurement
]  # fmt: skip


if __name__ == '__main__':
    main = report.experiment_main
    raise SystemExit(main(__doc__, 'live', OPTIONS, run, render, worker=run_child))
