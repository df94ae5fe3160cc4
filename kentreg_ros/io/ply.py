"""PLY point clouds (binary little/big endian and ASCII): the vertex element's x, y, z and extra
properties."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import DTypeLike

from kentreg_ros.io.errors import ScanFileError
from kentreg_ros.io.pointcloud2 import CloudArrays
from kentreg_ros.io.scanfiles import columns_of, finish_cloud, read_file_bytes

_PLY_TYPES = {
    'char': 'i1',
    'int8': 'i1',
    'uchar': 'u1',
    'uint8': 'u1',
    'short': 'i2',
    'int16': 'i2',
    'ushort': 'u2',
    'uint16': 'u2',
    'int': 'i4',
    'int32': 'i4',
    'uint': 'u4',
    'uint32': 'u4',
    'float': 'f4',
    'float32': 'f4',
    'double': 'f8',
    'float64': 'f8',
}


def _parse_ply_header(
    path: Path, raw: bytes
) -> tuple[str, list[tuple[str, int, list[tuple[str, str, bool]]]], int]:
    if not raw.startswith(b'ply'):
        raise ScanFileError(f'{path}: not a PLY file (no "ply" magic).')
    end = raw.find(b'end_header')
    if end < 0:
        raise ScanFileError(f'{path}: PLY header has no end_header (truncated?).')
    nl = raw.find(b'\n', end)
    if nl < 0:
        raise ScanFileError(f'{path}: PLY header is truncated after end_header.')
    lines = raw[:end].decode('ascii', errors='replace').splitlines()
    fmt = ''
    elements: list[tuple[str, int, list[tuple[str, str, bool]]]] = []
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ('comment', 'obj_info'):
            continue
        try:
            if words[0] == 'format':
                fmt = words[1]
            elif words[0] == 'element':
                elements.append((words[1], int(words[2]), []))
            elif words[0] == 'property':
                if not elements:
                    raise ScanFileError(f'{path}: PLY property before any element.')
                if words[1] == 'list':
                    elements[-1][2].append((words[4], words[3], True))
                else:
                    elements[-1][2].append((words[2], words[1], False))
            else:
                raise ScanFileError(f'{path}: unknown PLY header line {line!r}.')
        except (IndexError, ValueError) as exc:
            raise ScanFileError(f'{path}: malformed PLY header line {line!r}.') from exc
    if fmt not in ('ascii', 'binary_little_endian', 'binary_big_endian'):
        raise ScanFileError(f'{path}: unknown PLY format {fmt!r}.')
    for _, _, props in elements:
        for name, typ, _ in props:
            if typ not in _PLY_TYPES:
                raise ScanFileError(f'{path}: PLY property {name!r} has unknown type {typ!r}.')
    return fmt, elements, nl + 1


def read_ply(
    path: str | Path, *, fields: Sequence[str] | None = None, dtype: DTypeLike = np.float64
) -> CloudArrays:
    """Read the vertices of a PLY file (ascii or binary, either byte order).

    Parameters
    ----------
    path : str or Path
    fields : sequence of str, optional
        Extra vertex properties to keep (e.g. ``['scalar_intensity']``); None keeps all.
    dtype : {numpy.float64, numpy.float32}

    Returns
    -------
    CloudArrays

    Raises
    ------
    ScanFileError
        No vertex element or no x/y/z, truncated data, a list property in the vertex element
        (or, in binary files, in an element before it).
    """
    p = Path(path)
    raw = read_file_bytes(p)
    fmt, elements, start = _parse_ply_header(p, raw)
    names = [e[0] for e in elements]
    if 'vertex' not in names:
        raise ScanFileError(f'{p}: PLY has no vertex element (elements: {names}).')
    index = names.index('vertex')
    _, n, props = elements[index]
    if any(is_list for _, _, is_list in props):
        raise ScanFileError(f'{p}: PLY vertex element has list properties; not supported.')
    if fmt == 'ascii':
        lines = raw[start:].decode('ascii', errors='replace').splitlines()
        skip = sum(count for _, count, _ in elements[:index])
        rows = lines[skip : skip + n]
        if len(rows) < n:
            raise ScanFileError(
                f'{p}: PLY ascii vertex data is truncated: {len(rows)} of {n} rows.'
            )
        try:
            table = np.loadtxt(rows, dtype=np.float64, ndmin=2) if n else np.empty((0, 0))
        except ValueError as exc:
            raise ScanFileError(f'{p}: PLY ascii vertex data is malformed ({exc}).') from exc
        if n and table.shape[1] != len(props):
            raise ScanFileError(
                f'{p}: PLY ascii vertex rows have {table.shape[1]} values, expected {len(props)}.'
            )
        columns = {
            name: (table[:, i] if n else np.empty(0)).astype(_PLY_TYPES[typ])
            for i, (name, typ, _) in enumerate(props)
        }
    else:
        order = '<' if fmt == 'binary_little_endian' else '>'
        offset = start
        for name, count, eprops in elements[:index]:
            if any(is_list for _, _, is_list in eprops):
                raise ScanFileError(
                    f'{p}: PLY element {name!r} with list properties comes '
                    'before the vertices; not supported.'
                )
            offset += count * sum(np.dtype(_PLY_TYPES[t]).itemsize for _, t, _ in eprops)
        vdtype = np.dtype([(name, order + _PLY_TYPES[typ]) for name, typ, _ in props])
        need = n * vdtype.itemsize
        if len(raw) - offset < need:
            raise ScanFileError(
                f'{p}: PLY binary vertex data is truncated: {max(len(raw) - offset, 0)} bytes, '
                f'expected {n} * {vdtype.itemsize} = {need}.'
            )
        columns = columns_of(np.frombuffer(raw, vdtype, count=n, offset=offset))
    return finish_cloud(p, columns, fields, dtype)
