"""What every lln-* command shares: the exit contract, the model flags, the data folder, datasets.

Exit contract (docs/architecture.md): bad input = exit 2 and one line `PROG: error: ...` on stderr, checked before
anything long runs; a failure while running (a node died, a timeout) = exit 1 and `PROG: failed: ...`;
Ctrl-C (and SIGTERM / SIGHUP where asked) = exit 130. Flag defaults come from the core confs
(extractor / backbones / retrieval / similarity `default_conf`), never from literals here.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
from pathlib import Path

from ..errors import LLNError

DATA_ENV = 'LLN_DATA'  # the folder holding nordland_trimmed/, rtabmap_loop/ (the Makefile sets it)


class UsageError(LLNError):
    """Bad command-line values found after argparse (one line, exit 2)."""


class RunError(Exception):
    """The run failed after its inputs were accepted (a node died, a timeout): exit 1."""


class Terminated(KeyboardInterrupt):
    """SIGTERM / SIGHUP: cleaned up like Ctrl-C."""


def one_line(error: BaseException) -> str:
    """The message on one line (a library's multi-line text joined), so stderr keeps the contract."""
    return ' '.join(part.strip() for part in str(error).strip().splitlines() if part.strip()) or type(error).__name__


def run_cli(
    prog: str, run, *, error_status: int = 2, interrupted: str = 'interrupted', catch_signals: bool = False
) -> int:
    """run() -> exit status, with the exit contract above. error_status: the status of an LLNError
    (lln-map keeps 1, which its tests and scripts rely on). catch_signals: SIGTERM / SIGHUP are
    handled like Ctrl-C, so `finally` blocks stop child processes."""
    previous = {}
    if catch_signals:

        def terminate(signum, _frame):
            raise Terminated(f'signal {signum}')

        for sig in (signal.SIGTERM, signal.SIGHUP):
            try:
                previous[sig] = signal.signal(sig, terminate)
            except (ValueError, OSError):  # not the main thread
                pass
    try:
        return run()
    except LLNError as e:
        print(f'{prog}: error: {one_line(e)}', file=sys.stderr)
        return error_status
    except RunError as e:
        print(f'{prog}: failed: {e}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{prog}: {interrupted}', file=sys.stderr)
        return 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def progress_log(quiet: bool):
    """log(msg): a line on stderr, or nothing with --quiet."""
    return (lambda msg: None) if quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'must be a number, got {text!r}') from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f'must be positive, got {text}')
    return value


def parser_from_doc(prog: str, doc: str) -> argparse.ArgumentParser:
    """A parser whose description is the module doc's first line and whose epilog is the rest."""
    lines = doc.strip().splitlines()
    return argparse.ArgumentParser(
        prog=prog,
        description=lines[0],
        epilog='\n'.join(lines[1:]),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


# ------------------------------------------------------------------------------------- model flags


def add_model_arguments(p: argparse.ArgumentParser, weights: bool = True) -> None:
    """The extractor flags (lln-match, lln-reloc, lln-eval), defaults from the extractor's conf."""
    from ..core.extractor import default_conf as ext

    p.add_argument('--top-n', type=int, default=ext['top_n'], help=f'landmarks per image (default {ext["top_n"]})')
    p.add_argument(
        '--input-height',
        type=int,
        default=ext['input_height'],
        help=f'network input height (default {ext["input_height"]})',
    )
    p.add_argument(
        '--rand-seed',
        type=int,
        default=ext['rand_seed'],
        help=f"seed of RAND's cell locations, one fixed draw per grid (default {ext['rand_seed']})",
    )
    p.add_argument('--backbone', default=ext['backbone']['name'], help=f'default {ext["backbone"]["name"]}')
    p.add_argument('--layer', default=ext['backbone']['layer'], help="backbone feature layer (default: the backbone's)")
    p.add_argument(
        '--backbone-weights',
        default=ext['backbone']['weights_path'],
        help='local backbone state dict (resnet101 needs one)',
    )
    if weights:
        p.add_argument('--weights', default=ext['weights'], help='LLN head checkpoint (default: the shipped one)')
    add_runtime_argument(p)


def add_runtime_argument(p: argparse.ArgumentParser) -> None:
    """--runtime, for every command that builds an Extractor (the default lives in its default_conf)."""
    p.add_argument(
        '--runtime',
        default=None,
        help='what runs the network: onnxruntime | torch (default onnxruntime, torch when ONNX Runtime is '
        'not installed; the landmarks are the same) | onnxruntime-int8 (the backbone quantised: faster, '
        'close landmarks). Checked by the extractor, as its conf is',
    )


def runtime_conf(args) -> dict:
    """{'runtime': ...} when --runtime was given, else {} (the extractor's default applies)."""
    return {'runtime': args.runtime} if getattr(args, 'runtime', None) else {}


def add_prefilter_argument(p: argparse.ArgumentParser, what: str = 'first-stage candidates reranked') -> None:
    """--prefilter and --prefilter-k, defaults from retrieval.default_conf (one source)."""
    from ..core.landmark_index import PREFILTERS
    from ..core.retrieval import default_conf as retrieval

    first, k = retrieval['prefilter'], retrieval['prefilter_k']
    p.add_argument(
        '--prefilter',
        default=first,
        choices=PREFILTERS,
        help="first stage the rerank starts from: landmarks (each query landmark's nearest map "
        "landmarks, voted per reference), holistic (global cosine, the paper's) or exhaustive "
        f'(every reference) (default {first})',
    )
    p.add_argument(
        '--prefilter-k',
        type=int,
        default=k,
        help=f'{what} (default {k}; 0 = every reference, an exhaustive rerank, whatever --prefilter says)',
    )


def add_scale_argument(p: argparse.ArgumentParser) -> None:
    from ..core.similarity import default_conf as similarity

    p.add_argument(
        '--scale',
        type=float,
        default=similarity['scale'],
        help=f'offset-weight width in grid cells (default {similarity["scale"]:g})',
    )


def extractor_conf(args, **extra) -> dict:
    """The Extractor conf of the model flags (add_model_arguments)."""
    conf = {
        'backbone': {'name': args.backbone, 'layer': args.layer, 'weights_path': args.backbone_weights},
        'top_n': args.top_n,
        'input_height': args.input_height,
        'rand_seed': args.rand_seed,
    }
    if getattr(args, 'weights', None) is not None and isinstance(args.weights, str):
        conf['weights'] = args.weights
    return {**conf, **runtime_conf(args), **extra}


def check_output_file(path: str | None, flag: str) -> None:
    """--plot FILE and the like: its folder must exist before the expensive work starts."""
    if path:
        parent = Path(path).expanduser().resolve().parent
        if not parent.is_dir():
            raise UsageError(f'{flag} {path}: folder {parent} does not exist')
        if Path(path).is_dir():
            raise UsageError(f'{flag} {path} is a folder, not a file')


# ------------------------------------------------------------------------------------------- data


def data_dir() -> Path | None:
    """The shared data folder named by $LLN_DATA (scripts/ and the Makefile set it to ../shared/data
    of a checkout), when it holds the Nordland traverses; installed code never guesses a path."""
    value = os.environ.get(DATA_ENV)
    if not value:
        return None
    d = Path(value).expanduser()
    if (d / 'nordland_trimmed' / 'summer').is_dir() and (d / 'nordland_trimmed' / 'winter').is_dir():
        return d
    return None


def read_dataset(spec: str, frac, download: bool):
    """(Dataset or None when it must be downloaded first, the --range it got). Every image is read
    and checked by the dataset readers; a gardenspoint: folder without its traverses is None with
    --download, else a DatasetError saying to add --download."""
    from ..errors import DatasetError
    from ..io import datasets
    from ..io.download import GARDENS_POINT_FOLDERS

    kind, _, rest = spec.partition(':')
    if kind == 'gardenspoint':
        parts = [a for a in rest.split(',') if a]
        if len(parts) in (1, 3):
            root = Path(parts[0])
            need = parts[1:] or ['day_right', 'night_right']
            if not all((root / f).is_dir() for f in need):
                if download:
                    return None, None
                raise DatasetError(
                    f'{root} is not the Gardens Point Walking layout '
                    f'({", ".join(f + "/" for f in GARDENS_POINT_FOLDERS)}); '
                    f'add --download to fetch GardensPoint_Walking.zip into it'
                )
    use = frac if kind == 'aligned' else None
    ds = datasets.parse_spec(spec, use)
    if use:
        ds.name = f'{ds.name}[{use[0]:g}:{use[1]:g}]'
    return ds, use


def download_dataset(prog: str, spec: str, url: str | None, quiet: bool, log):
    """Fetch the Gardens Point traverses that read_dataset found missing, then read the dataset."""
    from ..io import datasets, download

    root = spec.partition(':')[2].split(',')[0]
    url = url or download.GARDENS_POINT_URL
    log(f'{prog}: {root} lacks the Gardens Point folders; downloading {url}')
    download.fetch_gardenspoint(root, url, progress=not quiet)
    return datasets.parse_spec(spec)
