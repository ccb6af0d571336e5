"""lln-map: look after a map (either backend; see lln_ros.mapstore.backend_for for map URIs).

    lln-map info MAP [--json]          keyframes, model, backend, index, bytes on disk
    lln-map check MAP                  what is wrong with a map, if anything (exit 1 when damaged)
    lln-map compact MAP                give deleted keyframes' space back (SQLite VACUUM / Milvus compact)
    lln-map export MAP DEST            copy every keyframe of MAP into DEST (ids and stamps kept)
    lln-map import MAP SRC             copy every keyframe of SRC into MAP (ids kept: taken ids refused)
    lln-map merge A B [C ...] DEST     every keyframe of A, B, ... into DEST (new or existing) under new
                                       ids, each once; robots and sessions kept (mapstore/merge.py)

A copy carries each keyframe's landmarks, stamp, geometry, verify keypoints and (robot, session,
seq) identity.

MAP, DEST, SRC: a path (SQLite), milvus-lite:///path.db or milvus://host:port[/db][?map=name].

Exit status: 0 done (check: healthy); 1 check found problems, or a failure while running; 2 bad
input, one line naming the map and the problem: no such map, not a map, a damaged model record, a
copy the destination refuses (ids taken, another model). Times print in ISO 8601 (UTC).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from datetime import datetime, timezone

from ..errors import MapError
from .common import UsageError, run_cli


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='lln-map',
        description=__doc__.strip().splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog='\n'.join(__doc__.strip().splitlines()[2:]),
    )
    sub = p.add_subparsers(dest='command', required=True)
    info = sub.add_parser('info', help='describe a map')
    info.add_argument('map')
    info.add_argument('--json', action='store_true', help='one JSON object')
    sub.add_parser('check', help='find damage').add_argument('map')
    sub.add_parser('compact', help='reclaim space').add_argument('map')
    export = sub.add_parser('export', help='copy MAP into DEST')
    export.add_argument('map')
    export.add_argument('dest')
    imp = sub.add_parser('import', help='copy SRC into MAP')
    imp.add_argument('map')
    imp.add_argument('src')
    merge = sub.add_parser('merge', help='merge maps into DEST under new ids')
    merge.add_argument('maps', nargs='+', metavar='MAP', help='the maps to merge, then DEST')
    merge.add_argument(
        '--legacy-robot', help="robot id of keyframes from maps of before schema 3 (default: each map's file name)"
    )
    return p


def copy_map(src_uri: str, dst_uri: str) -> int:
    """Copy every keyframe of src into dst (created if missing), keeping ids and stamps; returns the
    count copied (keyframes dst holds already, by content, are not copied again)."""
    from ..mapstore import MapStore
    from ..mapstore.merge import merge_into

    with MapStore.open(src_uri, create=False) as src:
        if src.model is None:
            raise MapError(f'map {src.path} has no model record (never used); nothing to copy')
        with MapStore.open(dst_uri, model=src.model) as dst:
            return merge_into(dst, src, keep_ids=True).added


def merge_maps(sources: list[str], dst_uri: str, legacy_robot: str | None = None, out=print) -> dict:
    """`lln-map merge`: every source into dst under new ids (mapstore.merge); a DEST this call
    created is removed again when the merge fails, so it is never left half-merged."""
    from ..mapstore import MapStore
    from ..mapstore.merge import digests, merge_into
    from ..mapstore.uri import backend_for

    kind, location = backend_for(dst_uri)
    created = kind == 'sqlite' and not os.path.exists(os.path.expanduser(location))
    totals = {'read': 0, 'added': 0, 'present': 0}
    try:
        with MapStore.open(dst_uri) as dst:
            known = digests(dst)
            for uri in sources:
                with MapStore.open(existing_map(uri), create=False) as src:
                    r = merge_into(dst, src, legacy_robot=legacy_robot, known=known)
                out(f'{uri}: {r.read} keyframes, {r.added} added, {r.present} already in {dst_uri}')
                for key in totals:
                    totals[key] += getattr(r, key)
            totals['keyframes'] = len(dst)
            totals['sessions'] = len(dst.sessions())
    except BaseException:
        if created:
            path = os.path.abspath(os.path.expanduser(location))
            for leftover in (path, path + '-wal', path + '-shm', path + '.landmarks'):
                if os.path.exists(leftover):
                    os.remove(leftover)
        raise
    return totals


def check(uri: str) -> list[str]:
    """Problems of the map at uri; a map that cannot even be opened is one problem saying why."""
    from ..mapstore import MapStore

    try:
        store = MapStore.open(uri, create=False, verify=False)
    except MapError as e:
        return [f'cannot open: {e}']
    with store:
        return store.check()


def iso_time(epoch) -> str:
    """Seconds since the epoch -> '2026-12-01T20:50:00Z'; 0 / None (not recorded) -> 'unknown'."""
    if not epoch:
        return 'unknown'
    return datetime.fromtimestamp(float(epoch), timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')


def readable(info: dict) -> dict:
    """info with its times in ISO 8601 (the seconds kept as NAME_unix in JSON)."""
    out = {}
    for key, value in info.items():
        if key in ('created', 'updated', 'modified'):
            out[key] = iso_time(value)
            out[f'{key}_unix'] = value
        else:
            out[key] = value
    return out


def existing_map(uri: str) -> str:
    """uri, after checking that a local map is there (UsageError, exit 2, before anything opens)."""
    from ..mapstore.uri import backend_for

    kind, location = backend_for(uri)
    if kind == 'sqlite':
        path = os.path.expanduser(location)
        if not os.path.exists(path):
            raise UsageError(f'{uri}: no such map file')
    elif location.startswith('milvus-lite://'):
        path = os.path.expanduser(location[len('milvus-lite://') :])
        if not os.path.exists(path):
            raise UsageError(f'{uri}: no such Milvus Lite map ({path} does not exist)')
    return uri


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    # bad input (no map, not a map, a refused copy) exits 2 as every lln-* command; `check` exits 1
    # when it found problems: that is its answer, not an error
    return run_cli('lln-map', lambda: run(args))


def run(args) -> int:
    from ..mapstore import MapStore

    if args.command == 'info':
        with MapStore.open(existing_map(args.map), create=False) as store:
            info = readable(store.info())
        if args.json:
            print(json.dumps(info, default=str))
        else:
            for key, value in info.items():
                if not key.endswith('_unix'):
                    print(f'{key:16s} {value}')
    elif args.command == 'check':
        problems = check(existing_map(args.map))
        if problems:
            print(f'{args.map}: {len(problems)} problem(s)')
            for p in problems:
                print(f'  - {p}')
            return 1
        print(f'{args.map}: healthy')
    elif args.command == 'compact':
        with MapStore.open(existing_map(args.map), create=False) as store:
            result = store.compact()
        sizes = (
            f': {result["bytes_before"]} -> {result["bytes_after"]} bytes'
            if result
            else ' (Milvus compacts in the background)'
        )
        print(f'compacted {args.map}{sizes}')
    elif args.command == 'merge':
        if len(args.maps) < 2:
            raise UsageError('merge needs at least one map and DEST')
        *sources, dest = args.maps
        t = merge_maps(sources, dest, args.legacy_robot)
        print(
            f'merged {len(sources)} maps into {dest}: {t["added"]} keyframes added, {t["present"]} already there; '
            f'{t["keyframes"]} keyframes in {t["sessions"]} sessions'
        )
    else:
        src, dst = (args.map, args.dest) if args.command == 'export' else (args.src, args.map)
        n = copy_map(existing_map(src), dst)
        print(f'copied {n} keyframes from {src} to {dst}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
