"""Inference runtimes for the extractor's network: torch, or the same network in ONNX Runtime.

The network is the frozen backbone cut at the configured layer followed by the LLN head:

    rgb uint8 (B, H, W, 3), H and W multiples of 32
      -> features float32 (B, D, H/32, W/32), rounded to float16 precision
      -> logits   float32 (B, H/32, W/32)       (the head's 1x1 fuse output before its ReLU)

Both runtimes run this one graph (`ExtractorNetwork`), so they agree to float rounding; the float16
rounding of the features is inside the graph, before the head, as in the torch path.

    net = build_network('efficientnet_lite0', 'stage6', backbone, head, runtime='onnxruntime', num_threads=1)
    feats, logits = net(rgb_batch)            # numpy arrays
    net.runtime                               # the runtime that actually runs: 'onnxruntime' | 'torch'

'onnxruntime-int8' runs the same graph with the backbone's convolutions quantised to int8 (static,
per channel, QDQ; the head, the float16 rounding and the outputs stay float): about twice as fast on
a CPU with VNNI. Its features are close to, not equal to, the float graph's (test/test_inference_runtime.py
bounds the difference; docs/benchmarks.md measures speed and accuracy). The activation ranges are
calibrated once on CALIBRATION_VIEWS views of matplotlib's sample photograph and cached beside the
float graph.

ONNX Runtime runs a graph exported from torch once and cached: `cache_dir()/onnx/`, where
cache_dir() is $LLN_CACHE, else $XDG_CACHE_HOME/lln_ros, else ~/.cache/lln_ros. The file name is
keyed by backbone, layer, a fingerprint of the backbone and of the head weights and the graph version;
height and width are dynamic axes, so one file serves every input size. `lln-export` writes the same
file ahead of time (e.g. on a robot whose home is read-only at run time, with LLN_CACHE set).
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import logging
import os
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..errors import ModelError
from .lln import state_fingerprint

log = logging.getLogger(__name__)

RUNTIMES = ('torch', 'onnxruntime', 'onnxruntime-int8')
# bump when ExtractorNetwork or the export settings change: old cache files are then not reused
# (2: Pad nodes without the empty constant_value input, see _let_ort_fuse_pads)
GRAPH_VERSION = 2
OPSET = 17
# the int8 graph: bump when quantize_onnx's settings or its calibration images change
QUANT_VERSION = 2
CALIBRATION_VIEWS = 32  # 384x288 views of the sample photograph (io.image.photo_views)
# the backbone's first convolutions stay float: quantised, their error runs through the whole network.
# Median feature cosine to the float graph on 30 Nordland + 14 rtabmap_loop frames (2026-12-05):
# 0.976 with every convolution in int8, 0.990 with the first 3 float, 0.9945 with 6, 0.9947 with 9;
# keeping the last 1-8 float instead changed nothing (0.976). Time per frame stays ~6 ms (float ~10)
FLOAT_FIRST_CONVS = 6

# ONNX Runtime session settings, chosen by measurement (bench/bench_runtime_options.py; docs/benchmarks.md):
# no spinning, because on shared cores a spinning worker only takes time from the thread that has
# work; parallel execution, although the graph is one chain of convolutions, because at 2 threads it
# ran 9.6-10.2 ms per 384x288 frame where sequential ran 11.7-12.8 (four runs, 2026-12-02, quiet),
# with less CPU and no loss beside a competing process; at 1 thread the two are equal.
ORT_SESSION_CONFIG = {'session.intra_op.allow_spinning': '0', 'session.inter_op.allow_spinning': '0'}


def cache_dir() -> Path:
    """Where lln_ros keeps derived files (exported graphs): $LLN_CACHE, else the XDG cache dir."""
    if os.environ.get('LLN_CACHE'):
        return Path(os.path.expanduser(os.environ['LLN_CACHE']))
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return Path(base) / 'lln_ros'


class ExtractorNetwork(nn.Module):
    """Backbone + LLN head on uint8 RGB: the graph both runtimes run (shapes in the module doc)."""

    def __init__(self, backbone: nn.Module, head: nn.Module):
        super().__init__()
        self.backbone = backbone
        self.head = head

    def forward(self, rgb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = rgb.permute(0, 3, 1, 2).float() / 255.0
        # float16 precision: the feature cache stores float16, so live extraction and evaluation
        # from the cache see the same numbers (and agree on every ranking)
        feats = self.backbone(x).half().float()
        return feats, self.head.logits(feats)


class TorchNetwork:
    runtime = 'torch'

    def __init__(self, backbone: nn.Module, head: nn.Module):
        # threads: torch's pool is per process, so the caller sets it (Extractor does)
        self.net = ExtractorNetwork(backbone, head).eval()

    @torch.inference_mode()
    def __call__(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        feats, logits = self.net(torch.from_numpy(np.ascontiguousarray(rgb)))
        return feats.numpy(), logits.numpy()


def onnx_path(
    backbone_name: str, layer: str, backbone: nn.Module, head: nn.Module, root: str | os.PathLike | None = None
) -> Path:
    """Cache file of the exported graph for this backbone/layer/weights (dynamic height and width)."""
    name = (
        f'{backbone_name}_{layer}_b{state_fingerprint(backbone)}_h{state_fingerprint(head)}_v{GRAPH_VERSION}_dynhw.onnx'
    )
    return Path(root) / name if root else cache_dir() / 'onnx' / name


def export_onnx(backbone: nn.Module, head: nn.Module, path: str | os.PathLike) -> Path:
    """Export ExtractorNetwork to `path` (atomically; a half-written file never has the real name).

    The TorchScript-based exporter (dynamo=False) is used: it needs only torch and `onnx` (not
    onnxscript), works offline and keeps height/width dynamic. A backbone whose padding depends on
    the input size gives its `exportable()` copy (constant padding, exact for multiples of 32).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    exportable = getattr(backbone, 'exportable', None)
    net = ExtractorNetwork(exportable() if exportable else backbone, head).eval()
    dummy = torch.zeros(1, 288, 384, 3, dtype=torch.uint8)
    tmp = path.with_name(f'{path.name}.{os.getpid()}.tmp')
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter('ignore')  # tracer warnings about the size-dependent padding (see above)
            torch.onnx.export(
                net,
                (dummy,),
                str(tmp),
                dynamo=False,
                opset_version=OPSET,
                input_names=['rgb'],
                output_names=['features', 'logits'],
                dynamic_axes={
                    'rgb': {0: 'batch', 1: 'height', 2: 'width'},
                    'features': {0: 'batch', 2: 'rows', 3: 'cols'},
                    'logits': {0: 'batch', 1: 'rows', 2: 'cols'},
                },
            )
        _let_ort_fuse_pads(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _let_ort_fuse_pads(path: Path) -> None:
    """Drop the empty optional `constant_value` input torch gives every Pad node.

    ONNX Runtime folds a zero Pad into the next Conv's pads (its PadFusion) only when every input
    of the Pad is a constant, and an empty name is not one. Unfused, each of the backbone's 16 Pads
    takes the tensor out of ORT's blocked NCHWc layout and back: 11 of 30 ms per 384x288 frame on
    one thread of this machine went to Pad and the two reorders. The values are unchanged (the
    omitted constant_value defaults to 0, which is what torch wrote)."""
    import onnx

    model = onnx.load(str(path))
    changed = False
    for node in model.graph.node:
        if node.op_type == 'Pad':
            while len(node.input) > 2 and node.input[-1] == '':
                node.input.pop()
                changed = True
    if changed:
        onnx.save(model, str(path))


def ensure_onnx(
    backbone_name: str, layer: str, backbone: nn.Module, head: nn.Module, root: str | os.PathLike | None = None
) -> Path:
    """The cached graph for this model, exported first when missing. Concurrent processes (nodes
    started together) wait on a lock file instead of exporting the same graph twice."""
    path = onnx_path(backbone_name, layer, backbone, head, root)
    if path.is_file():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + '.lock'), 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not path.is_file():
            log.info('exporting the %s/%s network to %s (once; cached)', backbone_name, layer, path)
            export_onnx(backbone, head, path)
    return path


def quantize_onnx(src: str | os.PathLike, dst: str | os.PathLike, images: list[np.ndarray] | None = None) -> Path:
    """Write the int8 copy of the float graph `src` to `dst` (atomically): static quantisation of the
    backbone (every node under /backbone/: per-channel int8 weights, uint8 activations, QDQ format)
    with activation ranges from `images` (RGB uint8 (H, W, 3), H and W multiples of 32; default
    CALIBRATION_VIEWS views of the sample photograph). Float stay: the backbone's first
    FLOAT_FIRST_CONVS convolutions, and the head and everything after the backbone (the landmark
    scores are what selection sorts by, and they cost nothing)."""
    import onnx
    from onnxruntime import quantization as q

    from ..io.image import photo_views

    images = photo_views(CALIBRATION_VIEWS, 384) if images is None else images
    dst = Path(dst)
    tmp = dst.with_name(f'{dst.name}.{os.getpid()}.tmp')
    pre = dst.with_name(f'{dst.name}.{os.getpid()}.pre.onnx')

    class Views(q.CalibrationDataReader):
        def __init__(self):
            self.feeds = iter({'rgb': np.ascontiguousarray(im, np.uint8)[None]} for im in images)

        def get_next(self):
            return next(self.feeds, None)

    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter('ignore')
            q.quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
            nodes = onnx.load(str(pre)).graph.node
            keep_float = [n.name for n in nodes if not n.name.startswith('/backbone/')]
            keep_float += [n.name for n in nodes if n.op_type == 'Conv' and n.name.startswith('/backbone/')][
                :FLOAT_FIRST_CONVS
            ]
            q.quantize_static(
                str(pre),
                str(tmp),
                Views(),
                quant_format=q.QuantFormat.QDQ,
                per_channel=True,
                activation_type=q.QuantType.QUInt8,
                weight_type=q.QuantType.QInt8,
                calibrate_method=q.CalibrationMethod.MinMax,
                nodes_to_exclude=keep_float,
            )
        os.replace(tmp, dst)
    finally:
        for f in (tmp, pre):
            f.unlink(missing_ok=True)
    return dst


def ensure_int8(float_path: Path) -> Path:
    """The cached int8 copy of the float graph at float_path, quantised first when missing (under
    the same kind of lock as ensure_onnx)."""
    path = float_path.with_name(float_path.name.replace('.onnx', f'_int8q{QUANT_VERSION}.onnx'))
    if path.is_file():
        return path
    with open(path.with_name(path.name + '.lock'), 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not path.is_file():
            log.info('quantising %s to int8 (once; cached as %s)', float_path.name, path.name)
            quantize_onnx(float_path, path)
    return path


def ort_session(path: str | os.PathLike, num_threads: int = 0):
    """An ONNX Runtime CPU session with the settings above; num_threads 0 = ORT's default."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = int(num_threads)
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_PARALLEL  # measured faster here: see ORT_SESSION_CONFIG
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3  # warnings about unused initializers etc. are noise to a user
    for key, value in ORT_SESSION_CONFIG.items():
        so.add_session_config_entry(key, value)
    return ort.InferenceSession(str(path), so, providers=['CPUExecutionProvider'])


class OnnxRuntimeNetwork:
    def __init__(self, path: str | os.PathLike, num_threads: int = 0, runtime: str = 'onnxruntime'):
        self.path = str(path)
        self.runtime = runtime  # 'onnxruntime' | 'onnxruntime-int8': what the graph file is
        self.session = ort_session(path, num_threads)

    def __call__(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if rgb.ndim != 4 or rgb.shape[1] % 32 or rgb.shape[2] % 32:
            # the graph's padding is exact for multiples of 32 only (backbones.EfficientNetLite.exportable)
            raise ModelError(f'the ONNX network takes (B, H, W, 3) with H and W multiples of 32, got {rgb.shape}')
        feats, logits = self.session.run(None, {'rgb': np.ascontiguousarray(rgb, dtype=np.uint8)})
        return feats, logits


def onnxruntime_available() -> bool:
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        return False
    return True


def build_network(
    backbone_name: str,
    layer: str,
    backbone: nn.Module,
    head: nn.Module,
    runtime: str = 'onnxruntime',
    num_threads: int = 0,
):
    """TorchNetwork or OnnxRuntimeNetwork. onnxruntime falls back to torch, with one log line,
    when ONNX Runtime is not installed or the graph cannot be exported or loaded; onnxruntime-int8
    falls back to the float graph when it cannot be quantised or loaded (network.runtime says which ran)."""
    if runtime not in RUNTIMES:
        raise ModelError(f'unknown runtime {runtime!r}; choose one of {list(RUNTIMES)}')
    if runtime == 'onnxruntime-int8' and onnxruntime_available():
        try:
            return _int8_network(ensure_onnx(backbone_name, layer, backbone, head), num_threads)
        except Exception as e:  # noqa: BLE001  the float graph still works
            log.warning('cannot run %s/%s in int8 (%s: %s): extracting in float', backbone_name, layer, *_why(e))
    if runtime.startswith('onnxruntime'):
        if not onnxruntime_available():
            log.warning('onnxruntime is not installed (pip install onnxruntime): extracting with torch')
        else:
            try:
                path = ensure_onnx(backbone_name, layer, backbone, head)
                try:
                    return OnnxRuntimeNetwork(path, num_threads)
                except Exception:  # noqa: BLE001  a damaged cache file: export it again, once
                    path.unlink(missing_ok=True)
                    return OnnxRuntimeNetwork(ensure_onnx(backbone_name, layer, backbone, head), num_threads)
            except Exception as e:  # noqa: BLE001  any exporter/runtime failure leaves torch working
                log.warning(
                    'cannot run %s/%s in onnxruntime (%s: %s): extracting with torch', backbone_name, layer, *_why(e)
                )
    return TorchNetwork(backbone, head)


def _int8_network(float_path: Path, num_threads: int) -> OnnxRuntimeNetwork:
    path = ensure_int8(float_path)
    try:
        return OnnxRuntimeNetwork(path, num_threads, 'onnxruntime-int8')
    except Exception:  # noqa: BLE001  a damaged cache file: quantise it again, once
        path.unlink(missing_ok=True)
        return OnnxRuntimeNetwork(ensure_int8(float_path), num_threads, 'onnxruntime-int8')


def _why(e: Exception) -> tuple[str, str]:
    return type(e).__name__, str(e).splitlines()[0] if str(e) else ''
