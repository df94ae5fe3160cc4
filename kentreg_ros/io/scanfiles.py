"""Scan files: PCD, PLY, KITTI ``.bin`` and the ETH local CSV format.

Every reader returns a :class:`~kentreg_ros.io.pointcloud2.CloudArrays`: finite points (N, 3),
the other fields aligned with them, and the number of non-finite points dropped. Readers parse
headers themselves and decode the point data with numpy structured dtypes (no Python loop over
points); malformed files raise :class:`~kentreg_ros.io.errors.ScanFileError` naming the file
and the problem.

Formats
-------
- PCD v0.5-0.7 (PCL), ``DATA ascii``, ``binary`` and ``binary_compressed`` (LZF, needs the
  ``python-lzf`` package). Binary data is little-endian, as PCL writes it.
- PLY (Turk 1994), ``ascii``, ``binary_little_endian`` and ``binary_big_endian``: the
  ``vertex`` element with scalar properties; other elements (faces, ...) are skipped when they
  come after it or have no list properties.
- KITTI Velodyne ``.bin``: float32 ``x y z reflectance`` records; reflectance is returned as
  ``intensity``.
- ETH "Challenging data sets" local CSV (Pomerleau et al., IJRR 2012): a header row naming the
  columns (``timestamp?, x, y, z, ...``), comma separated.
"""

from __future__ import annotations

import io
import logging
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

from kentreg_ros.io.errors import ScanFileError
from kentreg_ros.io.pointcloud2 import PADDING_FIELDS, CloudArrays

logger = logging.getLogger(__name__)

#: File suffixes :func:`read_scan` understands (lower case).
SCAN_SUFFIXES = ('.pcd', '.ply', '.bin', '.csv')
#: File names of pose files that may sit beside the scans; never listed as scans.
POSE_FILE_NAMES = frozenset({'pose_scanner_leica.csv', 'alidarpose.csv', 'poses.csv'})

_PCD_TYPES = {
    ('F', 4): 'f4',
    ('F', 8): 'f8',
    ('I', 1): 'i1',
    ('I', 2): 'i2',
    ('I', 4): 'i4',
    ('I', 8): 'i8',
    ('U', 1): 'u1',
    ('U', 2): 'u2',
    ('U', 4): 'u4',
    ('U', 8): 'u8',
}


def natural_key(name: str) -> tuple[Any, ...]:
    """Sort key ordering ``full2`` before ``full10`` (digit runs compare as numbers)."""
    parts = re.split(r'(\d+)', name)
    return tuple(int(p) if i % 2 else p.lower() for i, p in enumerate(parts))


def list_scans(folder: str | Path, *, suffixes: Iterable[str] | None = None) -> list[Path]:
    """Scan files of a folder in natural order (``full0, full1, ..., full10``).

    Parameters
    ----------
    folder : str or Path
    suffixes : iterable of str, optional
        Suffixes to accept (default :data:`SCAN_SUFFIXES`).

    Raises
    ------
    ScanFileError
        The folder does not exist, holds no scan, or mixes scan formats.
    """
    root = Path(folder)
    if not root.is_dir():
        raise ScanFileError(f'{root}: not a folder.')
    accept = {s.lower() for s in (suffixes or SCAN_SUFFIXES)}
    files = [
        p
        for p in root.iterdir()
        if p.is_file() and p.suffix.lower() in accept and p.name.lower() not in POSE_FILE_NAMES
    ]
    if not files:
        raise ScanFileError(f'{root}: no scan files ({", ".join(sorted(accept))}).')
    kinds = sorted({p.suffix.lower() for p in files})
    if len(kinds) > 1:
        counts = ', '.join(f'{sum(p.suffix.lower() == k for p in files)} {k}' for k in kinds)
        raise ScanFileError(f'{root}: mixes scan formats ({counts}); pass `suffixes`.')
    return sorted(files, key=lambda p: natural_key(p.name))


def read_scan(
    path: str | Path, *, fields: Sequence[str] | None = None, dtype: DTypeLike = np.float64
) -> CloudArrays:
    """Read one scan file, choosing the reader by suffix (.pcd, .ply, .bin, .csv).

    Parameters
    ----------
    path : str or Path
    fields : sequence of str, optional
        Extra fields to keep; None keeps all, ``()`` none.
    dtype : {numpy.float64, numpy.float32}
        dtype of the points.

    Returns
    -------
    CloudArrays
        ``stamp_ns`` is None and ``frame_id`` empty: files carry no time or frame.
    """
    from kentreg_ros.io.ply import read_ply  # it imports this module's helpers

    p = Path(path)
    readers = {'.pcd': read_pcd, '.ply': read_ply, '.bin': read_kitti_bin, '.csv': read_eth_csv}
    reader = readers.get(p.suffix.lower())
    if reader is None:
        raise ScanFileError(
            f'{p}: unknown scan format {p.suffix!r}; expected one of {", ".join(SCAN_SUFFIXES)}.'
        )
    return reader(p, fields=fields, dtype=dtype)


def read_file_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise ScanFileError(f'{path}: cannot read ({exc.strerror or exc}).') from exc


def finish_cloud(
    path: Path,
    columns: Mapping[str, NDArray[Any]],
    fields: Sequence[str] | None,
    dtype: DTypeLike,
) -> CloudArrays:
    """Assemble points and extras from named columns; drop non-finite points."""
    missing = [c for c in 'xyz' if c not in columns]
    if missing:
        raise ScanFileError(f'{path}: no {"/".join(missing)} field; fields are {list(columns)}.')
    out_dtype = np.dtype(dtype)
    if out_dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise ValueError(f'Expected `dtype` float64 or float32, got {out_dtype}.')
    names = [n for n in columns if n not in ('x', 'y', 'z')] if fields is None else list(fields)
    absent = [n for n in names if n not in columns]
    if absent:
        raise ScanFileError(f'{path}: no field {absent[0]!r}; fields are {list(columns)}.')
    n = len(columns['x'])
    points = np.empty((n, 3), out_dtype)
    for axis, c in enumerate('xyz'):
        points[:, axis] = columns[c]
    extras = {
        name: np.ascontiguousarray(columns[name], columns[name].dtype.newbyteorder('='))
        for name in names
        if name not in ('x', 'y', 'z')
    }
    n_dropped = 0
    if not np.isfinite(points).all():
        finite = np.isfinite(points[:, 0]) & np.isfinite(points[:, 1]) & np.isfinite(points[:, 2])
        n_dropped = n - int(np.count_nonzero(finite))
        points = points[finite]
        extras = {k: v[finite] for k, v in extras.items()}
    return CloudArrays(points, extras, n_dropped)


def columns_of(arr: NDArray[Any]) -> dict[str, NDArray[Any]]:
    """Fields of a structured array as plain arrays; padding fields are skipped."""
    names = arr.dtype.names or ()
    return {n: arr[n] for n in names if n not in PADDING_FIELDS}


# --- PCD -------------------------------------------------------------------------------------


def _parse_pcd_header(path: Path, raw: bytes) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b'\n', pos)
        if end < 0:
            raise ScanFileError(f'{path}: PCD header has no DATA line (truncated or not a PCD).')
        try:
            line = raw[pos:end].decode('ascii').strip()
        except UnicodeDecodeError as exc:
            raise ScanFileError(f'{path}: PCD header is not ASCII (not a PCD file?).') from exc
        pos = end + 1
        if not line or line.startswith('#'):
            continue
        key, *values = line.split()
        key = key.upper()
        if key == 'COLUMNS':  # PCD v0.5
            key = 'FIELDS'
        header[key] = values
        if key == 'DATA':
            return header, pos


def _pcd_int(path: Path, header: Mapping[str, list[str]], key: str) -> int:
    try:
        (value,) = header[key]
        number = int(value)
    except (KeyError, ValueError) as exc:
        raise ScanFileError(
            f'{path}: PCD header needs one integer {key}, got {header.get(key)!r}.'
        ) from exc
    if number < 0:
        raise ScanFileError(f'{path}: PCD header {key} is negative ({number}).')
    return number


def read_pcd(
    path: str | Path, *, fields: Sequence[str] | None = None, dtype: DTypeLike = np.float64
) -> CloudArrays:
    """Read a PCD file (``DATA ascii``, ``binary`` or ``binary_compressed``).

    Parameters
    ----------
    path : str or Path
    fields : sequence of str, optional
        Extra fields to keep (e.g. ``['intensity']``); None keeps all, ``()`` none.
    dtype : {numpy.float64, numpy.float32}

    Returns
    -------
    CloudArrays
        Points (N, 3) in file order, organised clouds flattened row-major, non-finite points
        dropped and counted. Fields with ``COUNT k > 1`` give (N, k) extras.

    Raises
    ------
    ScanFileError
        Missing or inconsistent header (``FIELDS``/``SIZE``/``TYPE``/``COUNT`` lengths,
        ``WIDTH * HEIGHT != POINTS``), an unknown type, or truncated data.
    """
    p = Path(path)
    raw = read_file_bytes(p)
    header, data_start = _parse_pcd_header(p, raw)
    names = header.get('FIELDS', [])
    sizes = header.get('SIZE', [])
    types = header.get('TYPE', [])
    counts = header.get('COUNT', ['1'] * len(names))
    if not names or not (len(names) == len(sizes) == len(types) == len(counts)):
        raise ScanFileError(
            f'{p}: PCD header FIELDS/SIZE/TYPE/COUNT differ in length '
            f'({len(names)}/{len(sizes)}/{len(types)}/{len(counts)}).'
        )
    width = _pcd_int(p, header, 'WIDTH')
    height = _pcd_int(p, header, 'HEIGHT') if 'HEIGHT' in header else 1
    n = _pcd_int(p, header, 'POINTS') if 'POINTS' in header else width * height
    if width * height != n:
        raise ScanFileError(
            f'{p}: PCD header WIDTH * HEIGHT = {width} * {height} = {width * height} but '
            f'POINTS = {n}.'
        )
    descr: list[tuple[Any, ...]] = []
    for i, (name, size, typ, count) in enumerate(zip(names, sizes, types, counts, strict=True)):
        try:
            code = _PCD_TYPES[(typ.upper(), int(size))]
            k = int(count)
        except (KeyError, ValueError) as exc:
            raise ScanFileError(
                f'{p}: PCD field {name!r} has unsupported TYPE {typ} SIZE {size} COUNT {count}.'
            ) from exc
        # '_' padding fields may repeat; give them unique names.
        key = f'_{i}' if name in PADDING_FIELDS else name
        descr.append((key, '<' + code, (k,)) if k > 1 else (key, '<' + code))
    try:
        point_dtype = np.dtype(descr)
    except ValueError as exc:
        raise ScanFileError(f'{p}: PCD FIELDS are not unique: {names}.') from exc
    (kind,) = header['DATA'] if len(header['DATA']) == 1 else ('?',)
    kind = kind.lower()
    body = memoryview(raw)[data_start:]
    if kind == 'ascii':
        arr = _pcd_ascii(p, body, point_dtype, n)
    elif kind == 'binary':
        need = n * point_dtype.itemsize
        if len(body) < need:
            raise ScanFileError(
                f'{p}: PCD binary data is truncated: {len(body)} bytes, expected POINTS * '
                f'point size = {n} * {point_dtype.itemsize} = {need}.'
            )
        if len(body) > need:
            logger.warning('%s: %d byte(s) after the PCD point data ignored.', p, len(body) - need)
        arr = np.frombuffer(body, point_dtype, count=n)
    elif kind == 'binary_compressed':
        arr = _pcd_binary_compressed(p, body, point_dtype, n)
    else:
        raise ScanFileError(
            f'{p}: unknown PCD DATA {" ".join(header["DATA"])!r}; expected '
            'ascii, binary or binary_compressed.'
        )
    columns = {k: v for k, v in columns_of(arr).items() if not re.fullmatch(r'_\d+', k)}
    return finish_cloud(p, columns, fields, dtype)


def _pcd_ascii(path: Path, body: memoryview, point_dtype: np.dtype[Any], n: int) -> NDArray[Any]:
    ncols = sum(int(np.prod(point_dtype[k].shape)) or 1 for k in point_dtype.names or ())
    text = bytes(body).decode('ascii', errors='replace')
    if n == 0:
        return np.empty(0, point_dtype)
    try:
        table = np.loadtxt(io.StringIO(text), dtype=np.float64, ndmin=2, comments='#')
    except ValueError as exc:
        raise ScanFileError(f'{path}: PCD ascii data is malformed ({exc}).') from exc
    if table.shape[0] != n or table.shape[1] != ncols:
        raise ScanFileError(
            f'{path}: PCD ascii data has {table.shape[0]} rows of {table.shape[1]} values; '
            f'header says POINTS {n} with {ncols} values per point.'
        )
    arr = np.empty(n, point_dtype)
    col = 0
    for name in point_dtype.names or ():
        width = int(np.prod(point_dtype[name].shape)) or 1
        block = table[:, col : col + width]
        arr[name] = block if point_dtype[name].shape else block[:, 0]
        col += width
    return arr


def _pcd_binary_compressed(
    path: Path, body: memoryview, point_dtype: np.dtype[Any], n: int
) -> NDArray[Any]:
    if len(body) < 8:
        raise ScanFileError(f'{path}: PCD binary_compressed data is truncated (no sizes).')
    compressed_size, raw_size = np.frombuffer(body[:8], '<u4')
    compressed_size, raw_size = int(compressed_size), int(raw_size)
    need = n * point_dtype.itemsize
    if raw_size != need:
        raise ScanFileError(
            f'{path}: PCD binary_compressed holds {raw_size} bytes, expected POINTS * point '
            f'size = {n} * {point_dtype.itemsize} = {need}.'
        )
    if len(body) - 8 < compressed_size:
        raise ScanFileError(
            f'{path}: PCD binary_compressed data is truncated: {len(body) - 8} of '
            f'{compressed_size} compressed bytes.'
        )
    if n == 0:
        return np.empty(0, point_dtype)
    try:
        import lzf
    except ImportError as exc:
        raise ScanFileError(
            f'{path}: PCD binary_compressed needs the python-lzf package (pip install '
            'python-lzf, or the io extra of kentreg_ros).'
        ) from exc
    try:
        plain = lzf.decompress(bytes(body[8 : 8 + compressed_size]), raw_size)
    except ValueError as exc:
        plain = None
        cause: Exception | None = exc
    else:
        cause = None
    if plain is None or len(plain) != raw_size:
        raise ScanFileError(f'{path}: PCD binary_compressed data is corrupt (LZF).') from cause
    # The decompressed block is field-major: all values of field 0, then field 1, ...
    arr = np.empty(n, point_dtype)
    offset = 0
    for name in point_dtype.names or ():
        fdt = point_dtype[name]
        k = int(np.prod(fdt.shape)) if fdt.shape else 1
        values = np.frombuffer(plain, fdt.base, count=n * k, offset=offset)
        arr[name] = values.reshape((n,) + fdt.shape)
        offset += n * fdt.itemsize
    return arr


def write_pcd(
    path: str | Path,
    points: ArrayLike,
    extra: Mapping[str, ArrayLike] | None = None,
    *,
    data: str = 'binary',
) -> None:
    """Write points (and per-point fields) as a PCD v0.7 file.

    Parameters
    ----------
    path : str or Path
    points : array_like, shape (N, 3)
        Written as float32 unless given as float64.
    extra : dict of str to array_like, each shape (N,) or (N, k), optional
    data : {'binary', 'ascii', 'binary_compressed'}
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f'Expected `points` to have shape (N, 3), got {pts.shape}.')
    xyz = np.dtype('<f8') if pts.dtype == np.float64 else np.dtype('<f4')
    columns = {'x': pts[:, 0], 'y': pts[:, 1], 'z': pts[:, 2]}
    columns.update({k: np.asarray(v) for k, v in (extra or {}).items()})
    n = len(pts)
    descr: list[tuple[Any, ...]] = []
    sizes, types, counts = [], [], []
    for name, values in columns.items():
        if len(values) != n:
            raise ValueError(f'Expected field {name!r} to have {n} values, got {len(values)}.')
        dt = xyz if name in 'xyz' else values.dtype.newbyteorder('<')
        if dt.kind not in 'iuf':
            raise ValueError(f'PCD cannot hold field {name!r} of dtype {values.dtype}.')
        k = int(np.prod(values.shape[1:])) if values.ndim > 1 else 1
        descr.append((name, dt, (k,)) if k > 1 else (name, dt))
        sizes.append(str(dt.itemsize))
        types.append({'f': 'F', 'i': 'I', 'u': 'U'}[dt.kind])
        counts.append(str(k))
    arr = np.empty(n, np.dtype(descr))
    for name, values in columns.items():
        arr[name] = values.reshape(arr[name].shape)
    head = (
        '# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n'
        f'FIELDS {" ".join(columns)}\nSIZE {" ".join(sizes)}\nTYPE {" ".join(types)}\n'
        f'COUNT {" ".join(counts)}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n'
        f'POINTS {n}\nDATA {data}\n'
    ).encode('ascii')
    if data == 'binary':
        body = arr.tobytes()
    elif data == 'ascii':
        flat = np.column_stack([arr[k].reshape(n, -1).astype(np.float64) for k in columns])
        # Shortest formats that round-trip each type exactly.
        fmts = [
            {'f': '%.9g' if arr.dtype[k].base.itemsize <= 4 else '%.17g'}.get(
                arr.dtype[k].base.kind, '%d'
            )
            for k in columns
            for _ in range(int(np.prod(arr.dtype[k].shape)) or 1)
        ]
        buf = io.StringIO()
        np.savetxt(buf, flat, fmt=fmts)
        body = buf.getvalue().encode('ascii')
    elif data == 'binary_compressed':
        import lzf

        plain = b''.join(np.ascontiguousarray(arr[k]).tobytes() for k in columns)
        packed = lzf.compress(plain) if plain else b''
        if packed is None:  # incompressible: LZF refuses to expand; store as literal runs
            packed = _lzf_literal(plain)
        body = np.array([len(packed), len(plain)], '<u4').tobytes() + packed
    else:
        raise ValueError(f'Expected `data` binary, ascii or binary_compressed, got {data!r}.')
    Path(path).write_bytes(head + body)


def _lzf_literal(plain: bytes) -> bytes:
    """LZF stream made of literal runs only (valid for any input, 1/32 larger)."""
    chunks = []
    for start in range(0, len(plain), 32):
        piece = plain[start : start + 32]
        chunks.append(bytes([len(piece) - 1]) + piece)
    return b''.join(chunks)


# --- KITTI and ETH ---------------------------------------------------------------------------


def read_kitti_bin(
    path: str | Path, *, fields: Sequence[str] | None = None, dtype: DTypeLike = np.float64
) -> CloudArrays:
    """Read a KITTI Velodyne ``.bin`` scan (float32 ``x y z reflectance`` records).

    Reflectance is returned as the extra field ``intensity``.

    Raises
    ------
    ScanFileError
        The file size is not a multiple of 16 bytes.
    """
    p = Path(path)
    raw = read_file_bytes(p)
    if len(raw) % 16:
        raise ScanFileError(
            f'{p}: KITTI .bin size {len(raw)} is not a multiple of 16 bytes (float32 x, y, z, '
            'reflectance); truncated or not a KITTI scan.'
        )
    arr = np.frombuffer(
        raw, np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])
    )
    return finish_cloud(p, columns_of(arr), fields, dtype)


def read_eth_csv(
    path: str | Path, *, fields: Sequence[str] | None = None, dtype: DTypeLike = np.float64
) -> CloudArrays:
    """Read a scan in the ETH local CSV format (``Hokuyo_<i>.csv``).

    The header row names the columns (case and spaces ignored); ``x``, ``y``, ``z`` are
    required, every other column (e.g. ``timestamp``) becomes a float64 extra.

    Raises
    ------
    ScanFileError
        No header, no x/y/z column, or rows with the wrong number of values.
    """
    p = Path(path)
    raw = read_file_bytes(p)
    text = raw.decode('utf-8', errors='replace')
    first, _, rest = text.partition('\n')
    names = [c.strip().lower() for c in first.strip().split(',')]
    if not names or any(not c for c in names) or not {'x', 'y', 'z'} <= set(names):
        raise ScanFileError(f'{p}: ETH CSV header must name x, y and z columns, got {first!r}.')
    try:
        table = np.loadtxt(io.StringIO(rest), delimiter=',', dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise ScanFileError(f'{p}: ETH CSV data is malformed ({exc}).') from exc
    if table.size and table.shape[1] != len(names):
        raise ScanFileError(
            f'{p}: ETH CSV rows have {table.shape[1]} values, header names {len(names)}.'
        )
    if not table.size:
        table = np.empty((0, len(names)))
    columns = {name: table[:, i] for i, name in enumerate(names)}
    return finish_cloud(p, columns, fields, dtype)
