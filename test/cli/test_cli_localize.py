"""``kentreg_localize`` (kentreg_ros.cli.localize) and the runs and scores it is built on
(kentreg_ros.eval.localization).

The map: the sample bag's even scans at their ``/ground_truth`` poses, written as a PLY with the
trajectory beside it (what ``~/save_map`` and the replay write); a few odd scans are held out.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scenes import corridor

from kentreg_ros.cli.__main__ import main as kentreg_main
from kentreg_ros.cli.localize import main
from kentreg_ros.eval import GroundTruth
from kentreg_ros.eval.localization import reference_frame_note
from kentreg_ros.io.mapfile import write_map
from kentreg_ros.io.poses import Trajectory, read_poses, write_tum
from kentreg_ros.io.recordings import open_recording
from kentreg_ros.io.scanfiles import write_pcd

ENTRY_KEYS = {'index', 'stamp_ns', 'status', 'T_map_scan', 'fit', 'message', 'ms', 'searched'}
HELD_OUT = (11, 27, 43)


@pytest.fixture(scope='module')
def site(repo_root: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``map/map.ply`` and ``map/trajectory_tum.txt`` of the even scans; ``odd/velodyne/`` holds
    the held-out scans as PCD with their reference in ``odd/poses_tum.txt``."""
    root = tmp_path_factory.mktemp('site')
    rec = open_recording(repo_root / 'bags' / 'balm_50')
    assert rec.reference is not None
    scans = list(rec.source)
    T = np.asarray(rec.reference.T_world_sensor)
    stamps = np.asarray(rec.reference.stamps_ns)
    even = list(range(0, len(scans), 2))
    world = np.concatenate([scans[i].points @ T[i, :3, :3].T + T[i, :3, 3] for i in even])
    (root / 'map').mkdir()
    write_map(root / 'map' / 'map.ply', world)
    write_tum(root / 'map' / 'trajectory_tum.txt', stamps[even], T[even])
    (root / 'odd' / 'velodyne').mkdir(parents=True)
    for k, i in enumerate(HELD_OUT):
        write_pcd(root / 'odd' / 'velodyne' / f'{k:06d}.pcd', np.asarray(scans[i].points))
    write_tum(root / 'odd' / 'poses_tum.txt', stamps[list(HELD_OUT)], T[list(HELD_OUT)])
    return {'map': root / 'map' / 'map.ply', 'odd': root / 'odd' / 'velodyne', 'root': root}


def _entries(out: Path) -> list[dict]:
    entries = json.loads((out / 'localization.json').read_text())
    assert isinstance(entries, list)
    for e in entries:
        assert set(e) == ENTRY_KEYS, e
        assert e['T_map_scan'] is None or np.asarray(e['T_map_scan']).shape == (4, 4)
    return entries


def test_global_each_localizes_held_out_scans_within_the_bars(
    site: dict[str, Path], repo_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Odd scans of the bag, whose /ground_truth holds the poses the map was built at: the
    comparison is in the map's frame."""
    out = tmp_path / 'out'
    bag = repo_root / 'bags' / 'balm_50'
    select = ['--start', '11', '--stride', '16', '--max-scans', '3']  # scans 11, 27, 43
    argv = [str(site['map']), str(bag), '--global-each', '--out', str(out), *select]
    assert main([*argv, '--no-progress']) == 0
    entries = _entries(out)
    assert [e['index'] for e in entries] == list(HELD_OUT)
    assert [e['status'] for e in entries] == ['localized'] * 3, [e['message'] for e in entries]
    assert len((out / 'poses_tum.txt').read_text().splitlines()) == 3
    assert (out / 'config.yaml').is_file()
    reference = json.loads((out / 'summary.json').read_text())['reference']
    assert reference['n_correct'] == 3 and reference['n_false_accepts'] == 0, reference
    printed = capsys.readouterr().out
    assert '3 within 0.5 m and 2 deg, false accepts 0' in printed


def test_a_reference_at_other_stamps_is_compared_only_when_told_it_shares_the_frame(
    site: dict[str, Path], tmp_path: Path
) -> None:
    """The held-out scans' own pose file shares no stamp with the map's trajectory: nothing
    says it is in the map's frame, unless --reference-in-map-frame does."""
    argv = [str(site['map']), str(site['odd']), '--global-each', '--max-scans', '1', '-q']
    assert main([*argv, '--out', str(tmp_path / 'a')]) == 0
    reference = json.loads((tmp_path / 'a' / 'summary.json').read_text())['reference']
    assert 'shares no stamp' in reference['not_compared']
    assert main([*argv, '--out', str(tmp_path / 'b'), '--reference-in-map-frame']) == 0
    reference = json.loads((tmp_path / 'b' / 'summary.json').read_text())['reference']
    assert reference['n_correct'] == 1, reference


def test_tracking_searches_until_scans_agree_then_places_every_scan(
    site: dict[str, Path], repo_root: Path, tmp_path: Path
) -> None:
    out = tmp_path / 'out'
    bag = repo_root / 'bags' / 'balm_50'
    assert main([str(site['map']), str(bag), '--max-scans', '5', '--out', str(out), '-q']) == 0
    entries = _entries(out)
    assert [e['status'] for e in entries] == ['searching'] * 2 + ['localized'] * 3
    assert [e['searched'] for e in entries] == [True] * 3 + [False] * 2
    assert [e['T_map_scan'] is None for e in entries] == [True] * 2 + [False] * 3
    placed = read_poses(out / 'poses_tum.txt')
    assert placed.stamps_ns is not None
    assert list(placed.stamps_ns) == [e['stamp_ns'] for e in entries[2:]]
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['mode'] == 'track' and summary['counts']['with_pose'] == 3
    assert summary['reference']['n_correct'] == 3
    assert summary['reference']['n_false_accepts'] == 0


def test_scans_of_another_place_are_never_localized(site: dict[str, Path], tmp_path: Path) -> None:
    """A corridor is nowhere in the sample's map: whatever fits best must be refused."""
    folder = tmp_path / 'corridor'
    folder.mkdir()
    rng = np.random.default_rng(4)
    hall = corridor(rng, 30_000)
    for k, x in enumerate((-10.0, 0.0, 10.0)):
        write_pcd(folder / f'{k:03d}.pcd', (hall - [x, 0.0, 0.0]).astype(np.float32))
    out = tmp_path / 'out'
    argv = [str(site['map']), str(folder), '--global-each', '--out', str(out), '--no-progress']
    assert main(argv) == 0
    entries = _entries(out)
    assert len(entries) == 3
    assert all(e['status'] != 'localized' and e['T_map_scan'] is None for e in entries), entries
    assert (out / 'poses_tum.txt').read_text() == ''


def test_a_missing_map_exits_2_with_one_line(
    site: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / 'nothing.ply'
    assert main([str(missing), str(site['odd']), '--out', str(tmp_path / 'o')]) == 2
    err = capsys.readouterr().err
    assert err == f'kentreg_localize: error: {missing}: no such file or folder\n'
    assert not (tmp_path / 'o').exists()
    assert kentreg_main(['localize', str(missing), str(site['odd'])]) == 2
    assert capsys.readouterr().err.startswith('kentreg_localize: error: ')
    argv = [str(site['map']), str(site['odd']), '--map-trajectory', str(missing)]
    assert main(argv) == 2
    assert capsys.readouterr().err.count('\n') == 1


def test_the_reference_is_compared_only_in_the_frame_the_map_was_built_in() -> None:
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (6, 1, 1))
    T[:, :3, 3] = rng.normal(size=(6, 3))
    stamps = np.arange(6, dtype=np.int64) * 100_000_000
    reference = GroundTruth(Trajectory(stamps, T), 'ref')
    assert reference_frame_note(Trajectory(stamps[::2], T[::2]), reference) == ''
    moved = T[::2].copy()
    moved[:, 0, 3] += 1.0  # a map built from other poses (an odometry's)
    assert 'not at the reference poses' in reference_frame_note(
        Trajectory(stamps[::2], moved), reference
    )
    assert 'no trajectory' in reference_frame_note(None, reference)
    assert 'no stamps' in reference_frame_note(Trajectory(None, T), reference)
    later = Trajectory(stamps + 10**12, T)
    assert 'shares no stamp' in reference_frame_note(later, reference)
