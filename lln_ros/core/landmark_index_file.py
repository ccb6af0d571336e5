"""The landmark index file (LandmarkIndex.write / LandmarkIndex.read): MAGIC, a 4-byte header
length, a JSON header (the owner's fields plus D, kind, landmark count, training size, centring,
whitening fingerprint, refine codes and the CRC-32 of what follows), the FAISS index, then for
'ivfpq-fs-refine' its refine codes. A file of another kind, centring, whitening or
landmark_index_top than the conf asks for is refused with a MapError, and its owner (a map store)
rebuilds it."""

from __future__ import annotations

import json
import os
import struct
import zlib

import faiss
import numpy as np

from ..errors import MapError
from . import whitening
from .refine_codes import RefineCodes

MAGIC = b'LLNLMIDX1\n'


def write(index, path: str, header: dict) -> None:
    """Serialise to path atomically (temporary file, fsync, rename): MAGIC, a JSON header
    (`header` plus D, kind, landmark count and the CRC-32 of what follows), the FAISS index, then
    for 'ivfpq-fs-refine' its refine codes (RefineCodes.to_bytes, header 'refine_bytes' long)."""
    blob = faiss.serialize_index(index.index)
    refine = index.refine.to_bytes() if index.refine is not None else b''
    head = json.dumps(
        {
            **header,
            'dim': index.dim,
            'kind': index.kind,
            'landmarks': index.ntotal,
            'trained_on': index.trained_on,
            'center': bool(index.conf['landmark_center']),
            'index_top': int(index.conf['landmark_index_top']),
            'whitening': whitening.fingerprint(index.whitening),
            **({'refine': index.refine.qtype, 'refine_bytes': len(refine)} if refine else {}),
            'crc32': zlib.crc32(refine, zlib.crc32(blob)),
        }
    ).encode()
    tmp = f'{path}.tmp-{os.getpid()}'
    try:
        with open(tmp, 'wb') as f:
            f.write(MAGIC + struct.pack('<I', len(head)) + head)
            f.write(memoryview(blob))
            f.write(refine)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        raise MapError(f'cannot write landmark index {path}: {e}') from e
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def read(cls, path: str, dim: int, conf: dict | None = None, space: str = '') -> tuple:
    """(index, header) from a file `write` made; MapError naming the problem when it is
    truncated, corrupt (CRC), of another descriptor size, not a landmark index at all, or of
    another kind or centring / whitening than `conf` asks for (its owner rebuilds it). Files
    written before the header recorded the kind are of the kind their FAISS type says."""
    try:
        with open(path, 'rb') as f:
            data = f.read()
    except OSError as e:
        raise MapError(f'cannot read landmark index {path}: {e}') from e
    try:
        if data[: len(MAGIC)] != MAGIC:
            raise ValueError('not an lln_ros landmark index (bad magic)')
        (n,) = struct.unpack('<I', data[len(MAGIC) : len(MAGIC) + 4])
        header = json.loads(data[len(MAGIC) + 4 : len(MAGIC) + 4 + n])
        blob = np.frombuffer(data, np.uint8, offset=len(MAGIC) + 4 + n)
        if zlib.crc32(blob) != header.get('crc32'):
            raise ValueError(f'checksum mismatch ({len(blob)} bytes of index data: truncated or corrupt)')
        size = int(header.get('refine_bytes', 0))
        refine = RefineCodes.from_bytes(int(dim), header['refine'], blob[len(blob) - size :]) if size else None
        index = faiss.deserialize_index(blob[: len(blob) - size])
    except (ValueError, KeyError, struct.error, RuntimeError) as e:
        raise MapError(f'landmark index {path} is unusable: {str(e).splitlines()[0][:200]}') from None
    if (
        index.d != int(dim)
        or not isinstance(index, (faiss.IndexIVFPQ, faiss.IndexIVFPQFastScan, faiss.IndexIDMap2))
        or index.ntotal != header.get('landmarks')
    ):
        raise MapError(
            f'landmark index {path} holds {type(index).__name__} of D={index.d} with '
            f'{index.ntotal} landmarks; expected D={dim} and {header.get("landmarks")}'
        )
    out = cls(dim, conf, space)
    if header.get('whitening', '') != whitening.fingerprint(out.whitening):
        raise MapError(
            f'landmark index {path} holds vectors whitened with {header.get("whitening") or "nothing"}; '
            f'this conf whitens with {whitening.fingerprint(out.whitening) or "nothing"}'
        )
    if bool(header.get('center', False)) != bool(out.conf['landmark_center']):
        # a file of an older lln_ros (raw descriptors) or of another setting: its vectors are not
        # what this conf searches with, so the owner rebuilds it from the stored descriptors
        raise MapError(
            f'landmark index {path} holds {"centred" if header.get("center") else "raw"} descriptors; '
            f'landmark_center is {bool(out.conf["landmark_center"])}'
        )
    if int(header.get('index_top', 0)) != int(out.conf['landmark_index_top']):
        raise MapError(
            f'landmark index {path} holds the best {header.get("index_top", 0)} landmarks of each keyframe '
            f'(0 = all); landmark_index_top is {out.conf["landmark_index_top"]}'
        )
    out.index, out.refine = index, refine
    if out.refine is not None and (out.refine.n != index.ntotal or out.kind != 'ivfpq-fs-refine'):
        raise MapError(f'landmark index {path} holds {out.refine.n} refine codes for {index.ntotal} landmarks')
    if isinstance(index, faiss.IndexIVF):
        if out.kind != out.conf['landmark_compressed']:
            # like centring and whitening: the owner rebuilds an index of another kind than asked
            raise MapError(
                f'landmark index {path} is {out.kind}; landmark_compressed is {out.conf["landmark_compressed"]}'
            )
        if out.refine is not None and out.refine.qtype != out.conf['landmark_refine']:
            raise MapError(
                f'landmark index {path} re-ranks on {out.refine.qtype}; '
                f'landmark_refine is {out.conf["landmark_refine"]}'
            )
        index.nprobe = out.nprobe()
    out.trained_on = int(header.get('trained_on', index.ntotal))
    return out, header
