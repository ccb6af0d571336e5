"""Fetching a public dataset that is not on disk yet: Gardens Point Walking for lln-eval / lln-demo
`--download` (never used by a test against the internet: test_eval serves a zip on loopback)."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import DatasetError

GARDENS_POINT_URL = 'https://www.tu-chemnitz.de/etit/proaut/datasets/GardensPoint_Walking.zip'
GARDENS_POINT_FOLDERS = ('day_left', 'day_right', 'night_right')


def _zip_layout(names: list[str], folders) -> str | None:
    """The prefix ('' or 'top/') under which every folder holds at least one image, or None."""
    from .datasets import IMAGE_SUFFIXES

    files = [n for n in names if not n.endswith('/')]
    prefixes = [''] + sorted({n.split('/')[0] + '/' for n in files if '/' in n})
    for pre in prefixes:
        if all(
            any(
                n.startswith(f'{pre}{f}/')
                and n.lower().endswith(IMAGE_SUFFIXES)
                and '/' not in n[len(pre) + len(f) + 1 :]
                for n in files
            )
            for f in folders
        ):
            return pre
    return None


def fetch_gardenspoint(
    root, url: str = GARDENS_POINT_URL, folders=GARDENS_POINT_FOLDERS, timeout: float = 60.0, progress: bool = True
) -> list[str]:
    """Download GardensPoint_Walking.zip into root, check it is a zip holding the expected traverse
    folders (at its top or under one top folder), and extract those folders into root. Folders that
    already exist in root are left alone. Returns the folders extracted. DatasetError on any problem
    (unreachable URL, truncated download, not a zip, corrupt member, missing folders, unsafe paths)."""
    import shutil
    import urllib.error
    import urllib.request
    import zipfile

    from tqdm import tqdm

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    part = root / '.GardensPoint_Walking.zip.part'
    try:
        try:
            with urllib.request.urlopen(url, timeout=timeout) as resp, open(part, 'wb') as fh:
                total = int(resp.headers.get('Content-Length') or 0)
                with tqdm(
                    total=total or None,
                    unit='B',
                    unit_scale=True,
                    desc=Path(url).name or 'download',
                    disable=not progress,
                ) as bar:
                    got = 0
                    for block in iter(lambda: resp.read(1 << 20), b''):
                        fh.write(block)
                        got += len(block)
                        bar.update(len(block))
        except (urllib.error.URLError, OSError, ValueError) as e:
            raise DatasetError(f'cannot download {url}: {getattr(e, "reason", None) or e}') from e
        if total and got != total:
            raise DatasetError(f'download of {url} is truncated: {got} of {total} bytes')
        if not zipfile.is_zipfile(part):
            head = part.read_bytes()[:16]
            raise DatasetError(f'{url} is not a zip archive ({got} bytes starting {head!r})')
        with zipfile.ZipFile(part) as z:
            names = z.namelist()
            unsafe = [n for n in names if n.startswith(('/', '\\')) or '..' in Path(n).parts or ':' in n]
            if unsafe:
                raise DatasetError(f'{url}: the archive holds unsafe paths, e.g. {unsafe[0]!r}')
            pre = _zip_layout(names, folders)
            if pre is None:
                tops = sorted({n.split('/')[0] for n in names})[:8]
                raise DatasetError(
                    f'{url}: the archive lacks the Gardens Point folders {"/, ".join(folders)}/ '
                    f'with images (its top level: {", ".join(tops) or "nothing"})'
                )
            bad = z.testzip()
            if bad is not None:
                raise DatasetError(f'{url}: archive member {bad!r} is corrupt')
            tmp = root / '.GardensPoint_Walking.extract'
            shutil.rmtree(tmp, ignore_errors=True)
            wanted = [f for f in folders if not (root / f).exists()]
            for n in names:
                for f in wanted:
                    if n.startswith(f'{pre}{f}/'):
                        z.extract(n, tmp)
            for f in wanted:  # move whole folders into place: no half-extracted traverse is ever visible
                os.replace(tmp / pre / f if pre else tmp / f, root / f)
            shutil.rmtree(tmp, ignore_errors=True)
        return wanted
    finally:
        part.unlink(missing_ok=True)
