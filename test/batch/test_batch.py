"""Tests of ``kentreg_batch``: the issue's six inputs on a real local Dask cluster, reruns,
interruptions, input discovery and bad arguments.

The cluster tests need the ``cluster`` extra (Dask's distributed scheduler); they skip without
it on a developer's machine and fail in CI, which installs it (test/run_tests.sh).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
from pathlib import Path

import pytest

from kentreg_ros.batch import InputStatus, discover_inputs, output_names
from kentreg_ros.batch.job import MARKER
from kentreg_ros.cli import batch as batch_cli
from kentreg_ros.cli.__main__ import main as kentreg_main
from kentreg_ros.cli.replay import main as replay_main

pytest.importorskip('rosbags', reason='the batch reads bags with rosbags')

#: Scans per input: enough for every output (ATE needs 3 poses), few for the tests' time.
SCANS = '5'
#: The replay's options the runs below share (the plot costs ~1 s an input; it is the
#: replay's own code either way).
OPTIONS = ['--max-scans', SCANS, '--no-plot', '--no-progress']
REPLAY_FILES = {
    'odometry.mcap',
    'poses_tum.txt',
    'poses_kitti.txt',
    'ground_truth_tum.txt',
    'config.yaml',
    'metrics.json',
}


@pytest.fixture
def cluster_extra() -> None:
    """Dask's distributed scheduler, or a skip (a failure in CI, where it is installed)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        if os.environ.get('CI'):
            pytest.fail(
                'CI installs the cluster extra (test/run_tests.sh); distributed is missing'
            )
        pytest.skip("the cluster extra is not installed (pip install -e '.[cluster]')")


def run(main: object, argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)  # type: ignore[operator]
    return code, out.getvalue(), err.getvalue()


def summary(out: Path) -> dict[str, dict[str, object]]:
    data = json.loads((out / 'summary.json').read_text())
    return {entry['name']: entry for entry in data['inputs']}


@pytest.fixture(scope='module')
def sample_bag(repo_root: Path) -> Path:
    bag = repo_root / 'bags' / 'balm_50'
    if not bag.is_dir():
        pytest.skip(f'sample bag {bag} is absent')
    return bag


@pytest.fixture
def fleet(sample_bag: Path, tmp_path: Path) -> Path:
    """The issue's six inputs: five copies of the sample bag and a corrupt MCAP file."""
    folder = tmp_path / 'fleet'
    folder.mkdir()
    for i in range(1, 6):
        shutil.copytree(sample_bag, folder / f'drive{i}')
    (folder / 'corrupt.mcap').write_bytes(b'\x89MCAP0\r\n' + bytes(range(256)) * 8)
    return folder


@pytest.mark.integration
def test_six_inputs_on_a_local_cluster_five_done_one_failed_a_rerun_skips_five(
    cluster_extra: None, fleet: Path, sample_bag: Path, tmp_path: Path
) -> None:
    out = tmp_path / 'out'
    code, stdout, stderr = run(
        batch_cli.main, [str(fleet), '--out', str(out), '--workers', '2', *OPTIONS]
    )
    assert code == 1, stderr
    entries = summary(out)
    assert sorted(entries) == ['corrupt', 'drive1', 'drive2', 'drive3', 'drive4', 'drive5']
    failed = entries.pop('corrupt')
    assert failed['status'] == 'failed' and failed['input'] == str(fleet / 'corrupt.mcap')
    assert 'corrupt.mcap' in str(failed['error']) and failed['scans'] is None
    assert f'failed     {fleet / "corrupt.mcap"}: ' in stdout and '5 done, 1 failed' in stdout
    assert not (out / 'corrupt' / MARKER).exists()
    for name, entry in entries.items():
        assert entry['status'] == 'done' and entry['error'] is None, entry
        assert entry['scans'] == int(SCANS) and entry['pairs'] == int(SCANS) - 1
        assert entry['failed_pairs'] == 0 and 0 < entry['ate_m'] < 0.05  # type: ignore[operator]
        assert entry['health'] == {
            'first': 1, 'ok': int(SCANS) - 1, 'recovered': 0, 'degenerate': 0, 'ambiguous': 0,
            'fell_back': 0, 'rejected': 0,
        }  # fmt: skip
        assert {p.name for p in (out / name).iterdir()} == REPLAY_FILES | {MARKER}
    table = (out / 'summary.md').read_text()
    assert '6 inputs: 5 done, 1 failed' in table and table.count('| done |') == 5

    # The same poses as kentreg_replay alone, in this process.
    alone = tmp_path / 'alone'
    code, _, stderr = run(replay_main, [str(sample_bag), '--out', str(alone), *OPTIONS])
    assert code == 0, stderr
    for name in entries:
        assert (out / name / 'poses_tum.txt').read_bytes() == (
            alone / 'poses_tum.txt'
        ).read_bytes()
        assert (out / name / 'config.yaml').read_text() == (alone / 'config.yaml').read_text()

    # A rerun skips the five (their outputs untouched) and tries the corrupt one again.
    stamps = {name: (out / name / MARKER).stat().st_mtime_ns for name in entries}
    code, stdout, stderr = run(
        batch_cli.main, [str(fleet), '--out', str(out), '--workers', '2', *OPTIONS]
    )
    assert code == 1, stderr
    again = summary(out)
    assert [again[n]['status'] for n in entries] == ['skipped'] * 5
    assert again['corrupt']['status'] == 'failed'
    assert {n: again[n]['ate_m'] for n in entries} == {n: e['ate_m'] for n, e in entries.items()}
    assert {name: (out / name / MARKER).stat().st_mtime_ns for name in entries} == stamps
    assert '1 failed, 5 skipped' in stdout


@pytest.mark.integration
def test_batch_joins_a_running_cluster_at_its_address(
    cluster_extra: None, sample_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A cluster started as a user starts one: Dask's defaults, so its workers have
    MALLOC_TRIM_THRESHOLD_ (which a task undoes); Dask's nanny sets it in this process too,
    and monkeypatch removes it afterwards."""
    from distributed import LocalCluster

    monkeypatch.setenv('MALLOC_TRIM_THRESHOLD_', '65536')
    out = tmp_path / 'out'
    with LocalCluster(n_workers=1, threads_per_worker=1, dashboard_address=None) as cluster:
        argv = [str(sample_bag), '--out', str(out), '--address', cluster.scheduler_address]
        code, stdout, stderr = run(batch_cli.main, [*argv, *OPTIONS])
    assert code == 0, stderr
    assert summary(out)['balm_50']['status'] == 'done'
    assert cluster.scheduler_address in stdout


@pytest.mark.integration
def test_in_process_batch_redoes_an_interrupted_input_and_skips_a_finished_one(
    sample_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without the cluster extra one worker runs in this process. An input whose folder has
    outputs but no marker (the batch was stopped in it) is run again from an empty folder."""
    monkeypatch.setattr(batch_cli, 'cluster_available', lambda: False)
    other = tmp_path / 'other' / 'balm_50'  # a second input of the same name
    shutil.copytree(sample_bag, other)
    out = tmp_path / 'out'
    argv = [str(sample_bag), str(other), '--out', str(out), *OPTIONS]
    code, stdout, stderr = run(batch_cli.main, argv)
    assert code == 0, stderr
    assert 'in this process' in stdout
    entries = summary(out)
    assert sorted(entries) == ['balm_50', 'balm_50-2']
    assert entries['balm_50-2']['input'] == str(other)
    (out / 'balm_50-2' / MARKER).unlink()
    (out / 'balm_50-2' / 'stale.txt').write_text('left by an interrupted run')
    code, stdout, stderr = run(batch_cli.main, argv)
    assert code == 0, stderr
    again = summary(out)
    assert again['balm_50']['status'] == 'skipped' and again['balm_50-2']['status'] == 'done'
    assert {p.name for p in (out / 'balm_50-2').iterdir()} == REPLAY_FILES | {MARKER}
    # With other parameters nothing is skipped: the outputs say what the command asked for.
    code, stdout, stderr = run(batch_cli.main, [*argv, '--set', 'odometry.model=local_map'])
    assert code == 0, stderr
    assert [e['status'] for e in summary(out).values()] == ['done', 'done']
    assert 'local_map' in (out / 'balm_50' / 'config.yaml').read_text()


def test_ctrl_c_leaves_the_summary_true_and_exits_130(
    sample_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kentreg_ros.core import Odometry

    monkeypatch.setattr(batch_cli, 'cluster_available', lambda: False)
    second = tmp_path / 'second'
    shutil.copytree(sample_bag, second)
    real_step = Odometry.step
    calls = []

    def step_then_ctrl_c(self: Odometry, *args: object, **kwargs: object) -> object:
        calls.append(1)
        if len(calls) == int(SCANS) + 2:  # the second input's second scan
            raise KeyboardInterrupt
        return real_step(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Odometry, 'step', step_then_ctrl_c)
    out = tmp_path / 'out'
    code, _, stderr = run(
        batch_cli.main, [str(sample_bag), str(second), '--out', str(out), *OPTIONS]
    )
    assert code == 130
    assert 'interrupted' in stderr and 'summary.json' in stderr
    data = json.loads((out / 'summary.json').read_text())
    assert data['complete'] is False
    assert [e['status'] for e in data['inputs']] == ['done', 'pending']
    assert (out / 'balm_50' / MARKER).is_file() and not (out / 'second' / MARKER).exists()
    assert '1 done, 1 pending' in (out / 'summary.md').read_text()


def test_more_workers_without_the_cluster_extra_say_what_to_install(
    sample_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(batch_cli, 'cluster_available', lambda: False)
    for extra in (['--workers', '2'], ['--address', 'tcp://127.0.0.1:1']):
        code, stdout, stderr = run(
            batch_cli.main, [str(sample_bag), '--out', str(tmp_path / 'o'), *extra]
        )
        assert code == 2 and stdout == ''
        (line,) = stderr.strip().splitlines()
        assert line.startswith(f'kentreg_batch: error: {extra[0]}')
        assert "pip install 'kentreg_ros[cluster]'" in line
    assert not (tmp_path / 'o').exists()


@pytest.mark.parametrize(
    ('argv', 'match'),
    [
        (['{tmp}/missing', '--out', '{tmp}/o'], 'missing: no such file or folder'),
        (['{tmp}/empty', '--out', '{tmp}/o'], 'no input in this folder'),
        (['{bag}', '--out', '{tmp}/o', '--workers', '0'], 'positive integer'),
        (['{bag}', '--out', '{tmp}/o', '--set', 'em.no_such_key=1'], 'Unknown parameter'),
        (['{bag}', '--out', '{tmp}/o', '--workers', '2', '--address', 'x:1'], '--workers'),
        (['{bag}'], '--out'),
    ],
)
def test_bad_arguments_exit_2_with_one_line(
    argv: list[str], match: str, sample_bag: Path, tmp_path: Path
) -> None:
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'empty' / 'notes.txt').write_text('no recording here')
    args = [a.format(tmp=tmp_path, bag=sample_bag) for a in argv]
    code, stdout, stderr = run(batch_cli.main, [*args, '--no-progress'])
    assert code == 2 and stdout == ''
    (line,) = stderr.strip().splitlines()
    assert line.startswith('kentreg_batch: error: ') and match in line
    assert not (tmp_path / 'o').exists()


def test_kentreg_batch_is_a_subcommand(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert kentreg_main(['batch', str(tmp_path / 'nothing'), '--out', str(tmp_path / 'o')]) == 2
    assert capsys.readouterr().err == (
        f'kentreg_batch: error: {tmp_path / "nothing"}: no such file or folder\n'
    )


def test_discovery_tells_an_input_folder_from_a_folder_of_inputs(tmp_path: Path) -> None:
    """A rosbag2 folder (metadata.yaml, or one storage file and no input below it) and a folder
    of scan files are one input each; any other folder is expanded one level, keeping its bag
    files, rosbag2 folders and scan folders in natural order."""
    root = tmp_path / 'fleet'
    (root / 'rosbag2').mkdir(parents=True)
    (root / 'rosbag2' / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    (root / 'rosbag2' / 'rosbag2_0.mcap').write_bytes(b'')
    (root / 'bare_bag').mkdir()
    (root / 'bare_bag' / 'bare_bag.mcap').write_bytes(b'')
    (root / 'scans10').mkdir()
    (root / 'scans10' / '000.pcd').write_bytes(b'')
    (root / 'scans2').mkdir()
    (root / 'scans2' / '000.bin').write_bytes(b'')
    (root / 'scans2' / 'poses.csv').write_text('')
    (root / 'drive.db3').write_bytes(b'')
    (root / 'notes.txt').write_text('')
    (root / '.hidden.mcap').write_bytes(b'')
    (root / 'nothing').mkdir()
    (root / 'only_poses').mkdir()
    (root / 'only_poses' / 'poses.csv').write_text('')
    assert discover_inputs([str(root)]) == [
        str(root / p) for p in ('bare_bag', 'drive.db3', 'rosbag2', 'scans2', 'scans10')
    ]
    for one in ('rosbag2', 'bare_bag', 'scans10'):
        assert discover_inputs([str(root / one)]) == [str(root / one)]
    assert discover_inputs([str(root / 'notes.txt')]) == [str(root / 'notes.txt')]
    # One stray .mcap beside bag folders does not make the folder a bag: six inputs.
    (root / 'stray.mcap').write_bytes(b'')
    assert len(discover_inputs([str(root)])) == 6
    # The same input twice (directly and through its folder) runs once.
    assert (
        discover_inputs([str(root / 'drive.db3'), str(root)]).count(str(root / 'drive.db3')) == 1
    )


def test_output_names_are_distinct_and_keep_another_inputs_finished_folder(tmp_path: Path) -> None:
    a, b, c = tmp_path / 'a' / 'run', tmp_path / 'b' / 'run', tmp_path / 'run.mcap'
    for folder in (a, b):
        folder.mkdir(parents=True)
    c.write_bytes(b'')
    assert output_names([str(a), str(b), str(c)]) == ['run', 'run-2', 'run-3']
    # 'run' holds b's finished output: b keeps it, a takes the next free name.
    finished = {'run': str(b.resolve())}
    assert output_names([str(a), str(b)], finished_by=finished.get) == ['run-2', 'run']


def test_input_status_values_are_the_summarys_words() -> None:
    assert [str(s) for s in InputStatus] == ['done', 'failed', 'skipped', 'pending']


def _worker_environment() -> dict[str, str | None]:
    names = ('MALLOC_TRIM_THRESHOLD_', 'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS')
    return {name: os.environ.get(name) for name in names}


@pytest.mark.integration
def test_local_cluster_workers_run_one_thread_without_dasks_malloc_trim(
    cluster_extra: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which pins glibc's mmap
    threshold and made a BALM scan 29 ms instead of 19: the batch's local cluster leaves it
    unset (in a process without it, as kentreg_batch starts), and holds the numeric libraries
    to one thread."""
    from kentreg_ros.batch import engine

    monkeypatch.delenv('MALLOC_TRIM_THRESHOLD_', raising=False)
    # The workers must get one thread from the engine, not from the tests' environment.
    monkeypatch.delenv('OMP_NUM_THREADS', raising=False)
    monkeypatch.delenv('OPENBLAS_NUM_THREADS', raising=False)
    with engine._client(workers=1, address=None, n_jobs=1) as (client, pids):
        (env,) = client.run(_worker_environment).values()
    assert len(pids) == 1
    assert env == {
        'MALLOC_TRIM_THRESHOLD_': None, 'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1',
    }  # fmt: skip
