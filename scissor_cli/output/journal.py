"""The trial journal: every finished trial, appended to a file no crash can spoil.

While a run has trials to do, `results.h5.journal` sits beside
`results.h5.tmp`. Each finished trial is appended to it (one `write` of a
framed, checksummed record) *before* it is stored in the HDF5 file, and the
journal is deleted once the file is closed and renamed. HDF5 makes no
promise about a file whose writer was killed in the middle of a write
(docs/contract.md#resume): the journal is what `--resume` trusts for the
trials, the HDF5 file for everything before them.

Format: a header record (the run's `config_yaml` and `seed`), then one
record per trial. A record is the 8-byte magic `b"SCJRNL01"`, the payload
length (uint64, little-endian), its CRC-32 (uint32), and the payload: an
`.npz` archive (no pickles) of the record's fields. A torn last record (the
run killed while appending) fails its length or checksum; it and anything
after it are ignored and cut off when the journal is continued.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from pathlib import Path
from typing import Iterator

import numpy as np

MAGIC = b"SCJRNL01"
HEAD = struct.Struct("<8sQI")


def journal_path(results_path: Path) -> Path:
    return results_path.with_name(results_path.name + ".journal")


def _encode(record: dict) -> bytes:
    buf = io.BytesIO()
    arrays = {}
    for key, value in record.items():
        if isinstance(value, (list, tuple)) and not value:
            arrays[key] = np.zeros(0, dtype="U1")
        else:
            arrays[key] = np.asarray(value)
    np.savez(buf, **arrays)
    payload = buf.getvalue()
    return HEAD.pack(MAGIC, len(payload), zlib.crc32(payload)) + payload


def _decode(payload: bytes) -> dict:
    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        out = {}
        for key in z.files:
            a = z[key]
            if a.ndim == 0:
                out[key] = a.item()
            elif a.dtype.kind == "U":
                out[key] = [str(s) for s in a]
            else:
                out[key] = a
        return out


def read(path: Path) -> tuple[dict | None, list[dict], int]:
    """(header, trial records, bytes of valid records): stops at the first torn or damaged record."""
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        return None, [], 0
    records, offset = [], 0
    while offset + HEAD.size <= len(data):
        magic, length, crc = HEAD.unpack_from(data, offset)
        payload = data[offset + HEAD.size: offset + HEAD.size + length]
        if magic != MAGIC or len(payload) != length or zlib.crc32(payload) != crc:
            break
        try:
            records.append(_decode(payload))
        except (ValueError, OSError, KeyError):
            break
        offset += HEAD.size + length
    if not records:
        return None, [], 0
    return records[0], records[1:], offset


class Journal:
    """An open journal, appended to one record at a time."""

    def __init__(self, path: Path, fd: int):
        self.path, self._fd = path, fd

    @classmethod
    def create(cls, path: Path, config_yaml: str, seed: int) -> "Journal":
        """A new journal (replacing any old one) starting with the run's header."""
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o644)
        journal = cls(path, fd)
        journal._write({"kind": "header", "config_yaml": config_yaml, "seed": int(seed)})
        return journal

    @classmethod
    def resume(cls, path: Path, valid_bytes: int) -> "Journal":
        """Continue an existing journal after its last intact record (a torn tail is cut off)."""
        fd = os.open(path, os.O_WRONLY | os.O_APPEND)
        os.ftruncate(fd, valid_bytes)
        return cls(path, fd)

    def append(self, record: dict) -> None:
        self._write(record)

    def _write(self, record: dict) -> None:
        data = _encode(record)
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def remove(self) -> None:
        self.close()
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass


def records(path: Path) -> Iterator[dict]:
    """The trial records of a journal, in the order they finished."""
    yield from read(path)[1]
