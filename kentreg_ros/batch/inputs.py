"""Which inputs a batch runs, and the output folder each one gets.

An argument is one input when the replay takes it as one (:func:`is_replay_input`): a file (a
bag file, or anything else, which then fails as the replay fails on it), a rosbag2 folder
(``metadata.yaml`` inside), a scan folder (scan files directly inside it,
:data:`~kentreg_ros.io.scanfiles.SCAN_SUFFIXES`), or a folder with a single ``.mcap``/``.db3``
file and no subfolder that is an input (a bag copied without its metadata). Any other folder is
a folder of inputs: its bag files, rosbag2 folders and scan folders, one level down, in natural
order; other entries (hidden ones, notes, folders of neither kind) are left out. So a folder of
bag folders beside one stray ``.mcap`` file is a folder of six inputs, not one bag.

Each input writes into ``<out>/<name>/``: its bag file's stem or its folder's name. Inputs that
would share a name get ``-2``, ``-3``, ... in the order given, and a folder already finished by
another input (its marker names that input) is passed over, so a rerun with the inputs in
another order writes over nothing.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterable
from pathlib import Path

from kentreg_ros.core import KentRegError
from kentreg_ros.io.bags import BAG_SUFFIXES, is_bag
from kentreg_ros.io.scanfiles import POSE_FILE_NAMES, SCAN_SUFFIXES, natural_key

logger = logging.getLogger(__name__)


class BatchInputError(KentRegError, ValueError):
    """An argument names no input: a missing path, or a folder with no input in it."""


def is_scan_folder(path: Path) -> bool:
    """Whether ``path`` is a folder with scan files directly inside it (a replay input)."""
    return path.is_dir() and any(
        p.is_file() and p.suffix.lower() in SCAN_SUFFIXES and p.name.lower() not in POSE_FILE_NAMES
        for p in path.iterdir()
    )


def is_replay_input(path: Path) -> bool:
    """Whether the replay takes ``path`` as one input (see the module docstring)."""
    if path.is_file() or (path / 'metadata.yaml').is_file() or is_scan_folder(path):
        return True
    return is_bag(path) and not any(
        p.is_dir() and not p.name.startswith('.') and is_replay_input(p) for p in path.iterdir()
    )


def discover_inputs(arguments: Iterable[str]) -> list[str]:
    """The inputs of the arguments, in the order given (a folder of inputs expanded in natural
    order), each once.

    Raises
    ------
    BatchInputError
        An argument does not exist, or is a folder with no input in it.
    """
    inputs: list[str] = []
    seen: set[Path] = set()
    for argument in arguments:
        path = Path(argument)
        if not path.exists():
            raise BatchInputError(f'{argument}: no such file or folder')
        if is_replay_input(path):
            found = [argument]
        else:
            found = [str(p) for p in _inputs_in(path)]
            if not found:
                raise BatchInputError(
                    f'{argument}: no input in this folder (bag files '
                    f'{", ".join(BAG_SUFFIXES)}, rosbag2 folders or folders of scan files)'
                )
        for item in found:
            key = Path(item).resolve()
            if key in seen:
                logger.info('%s is given twice; running it once.', item)
                continue
            seen.add(key)
            inputs.append(item)
    return inputs


def _inputs_in(folder: Path) -> list[Path]:
    entries = sorted(folder.iterdir(), key=lambda p: natural_key(p.name))
    found = []
    for entry in entries:
        if entry.name.startswith('.'):
            continue
        if entry.is_file() and entry.suffix.lower() in BAG_SUFFIXES:
            found.append(entry)
        elif entry.is_dir() and (is_bag(entry) or is_scan_folder(entry)):
            found.append(entry)
        else:
            logger.info('%s: not a bag, rosbag2 folder or scan folder; left out.', entry)
    return found


def output_names(
    inputs: Iterable[str], *, finished_by: Callable[[str], str | None] = lambda name: None
) -> list[str]:
    """One output folder name per input, distinct (see the module docstring).

    Parameters
    ----------
    inputs : iterable of str
    finished_by : callable, optional
        The input whose finished output a folder name already holds (its marker), or None.
    """
    names: list[str] = []
    for item in inputs:
        path = Path(item)
        base = path.stem if path.is_file() else path.resolve().name
        base = re.sub(r'[^\w.+-]', '_', base).lstrip('.') or 'input'
        own = str(path.resolve())
        n = 1
        while True:
            name = base if n == 1 else f'{base}-{n}'
            other = finished_by(name)
            if name not in names and (other is None or other == own):
                break
            n += 1
        names.append(name)
    return names
