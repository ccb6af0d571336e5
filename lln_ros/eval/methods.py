"""The rows lln-eval computes: methods, LLN heads (one `lln[label]` row each) and extractor variants."""

from __future__ import annotations

import copy
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..core.landmarks import METHODS as LOCAL_METHODS
from ..core.lln import LLNHead, head_fingerprint, load_checkpoint
from ..errors import ModelError
from ..io.datasets import image_keys
from .peers import PEER_METHODS

METHODS = ('holistic',) + tuple(LOCAL_METHODS)  # the paper's rows, the default
ALL_METHODS = METHODS + PEER_METHODS  # plus the classic peers (opt-in: --methods ...,sad,seqslam)
METRIC_KEYS = ('p_at_100r', 'r_at_1', 'r_at_5', 'r_at_10', 'auc_pr', 'r_at_100p')
REPORT_KEYS = METRIC_KEYS + ('extract_ms', 'match_ms_per_pair', 'n')


UNTRAINED_WORDS = ('', 'xavier', 'untrained', 'none')
SHIPPED_WORDS = ('shipped', 'default')
# extractor settings a head row may override (`LABEL=CKPT@act_fusion=0.5`): how its cells are
# chosen from its logits, so one run compares selection rules of the same head
SELECT_KEYS = ('act_fusion',)


@dataclass
class Head:
    """An LLN head to evaluate as its own `lln[label]` row.

    weights: a checkpoint path; None (or '', 'xavier', 'untrained') = a seeded Xavier-init head (the
    untrained baseline); 'shipped' = the head shipped for this backbone/layer; 'extractor' = the
    extractor's own head as configured. select: extractor settings (SELECT_KEYS) for this row only."""

    label: str
    weights: str | None
    module: LLNHead | None = None
    meta: dict = field(default_factory=dict)
    select: dict = field(default_factory=dict)

    @property
    def trained(self) -> bool:
        return bool(self.meta.get('trained', True))

    def held_out(self, ds) -> dict:
        """Whether this head saw dataset ds (its queries or references) in training or validation:
        {'status': 'held out' | 'validated on' | 'trained on' | 'untrained' | 'unknown', 'images': how
        many distinct images ds has, 'trained': how many of them the head trained on, 'validated': how
        many it was validated on}. 'unknown': the checkpoint does not list its images (written before
        lln-train kept them); 'validated on' matters because validation picks the kept epoch."""
        keys = set(image_keys([*ds.query_paths, *ds.ref_paths]))
        out = {'images': len(keys)}
        seen = self.meta.get('seen_images')
        if not self.trained:
            return {**out, 'status': 'untrained', 'trained': 0, 'validated': 0}
        if not seen:
            return {**out, 'status': 'unknown'}
        trained, validated = len(keys & set(seen['train'])), len(keys & set(seen['val']))
        status = 'trained on' if trained else 'validated on' if validated else 'held out'
        return {**out, 'status': status, 'trained': trained, 'validated': validated}


def parse_select(items: list[str]) -> dict:
    """['act_fusion=0.5', ...] -> {'act_fusion': 0.5}; ValueError naming a bad item."""
    out = {}
    for item in items:
        key, _, value = item.partition('=')
        if key not in SELECT_KEYS:
            raise ValueError(f'unknown head setting {key!r} in @{item}; choose from {SELECT_KEYS}')
        try:
            out[key] = float(value)
        except ValueError:
            raise ValueError(f'head setting @{item}: {value!r} is not a number') from None
    return out


def parse_head(text: str, label: str | None = None) -> Head:
    """'LABEL=PATH[@KEY=VALUE...]' or 'PATH' -> Head (not loaded). PATH '' / 'xavier' / 'untrained'
    = untrained; @KEY=VALUE: a selection setting of this row (SELECT_KEYS)."""
    if label is None and '=' in text.split('@')[0]:
        label, _, text = text.partition('=')
    text, *opts = text.split('@')
    select = parse_select(opts)
    weights = None if text.strip().lower() in UNTRAINED_WORDS else text
    if label is None:
        label = (
            'untrained' if weights is None else ('shipped' if weights.lower() in SHIPPED_WORDS else Path(weights).stem)
        )
    return Head(label.strip(), weights, select=select)


def load_heads(extractor, heads: list[Head] | None) -> list[Head]:
    """Build every head (checkpoint metadata must fit the extractor's backbone/layer/D). No heads =
    the extractor's own head as one unlabelled head (row 'lln').

    An untrained head is Xavier-initialised with the architecture and init seed of the first
    checkpoint among `heads` (so "trained vs untrained" differs only in training), or with the
    default LLNHead conf when no checkpoint is given."""
    if not heads:
        return [Head('', extractor.model_info.get('weights') or None, extractor.head, dict(extractor.head_meta))]
    name, layer, dim = extractor.conf['backbone']['name'], extractor.backbone.layer, extractor.backbone.dim
    labels = [h.label for h in heads]
    if len(set(labels)) != len(labels):
        raise ModelError(f'head labels must be distinct, got {labels}')
    out: list = [None] * len(heads)
    untrained = []
    for i, h in enumerate(heads):
        w = h.weights
        if h.module is not None:
            out[i] = h
        elif w is None or w.strip().lower() in UNTRAINED_WORDS:
            untrained.append(i)
        elif w == 'extractor':
            out[i] = Head(
                h.label,
                extractor.model_info.get('weights') or None,
                extractor.head,
                dict(extractor.head_meta),
                dict(h.select),
            )
        else:
            if w.lower() in SHIPPED_WORDS:
                from ..core.extractor import shipped_weights

                path = shipped_weights(name, layer)
                if not path:
                    raise ModelError(f'no LLN head ships for backbone {name!r} layer {layer!r}; pass a checkpoint path')
            else:
                path = os.path.expanduser(w)
            module, meta = load_checkpoint(path, name, layer, dim)
            out[i] = Head(h.label, path, module, meta, dict(h.select))
    arch = next((h.module.conf for h in out if h is not None and h.weights), None)
    for i in untrained:
        meta = {'trained': False, 'head_conf': arch}
        out[i] = Head(heads[i].label, None, LLNHead(dim, arch).eval(), meta, dict(heads[i].select))
    for h in out:
        for p in h.module.parameters():
            p.requires_grad_(False)
    return out


def variant(extractor, method: str, top_n: int, head: Head | None = None):
    """A shallow copy of the extractor with its own conf (method, top_n) and, optionally, another
    head. The backbone is shared: no second network is built."""
    v = copy.copy(extractor)
    v.conf = {**extractor.conf, **(head.select if head is not None else {}), 'method': method, 'top_n': int(top_n)}
    if head is not None:
        v.head, v.head_meta = head.module, head.meta
        v.model_info = {
            **extractor.model_info,
            'head': head_fingerprint(head.module),
            'head_trained': head.trained,
            'weights': head.weights or '',
        }
    return v


def row_names(methods, heads: list[Head]) -> list[tuple[str, str, Head | None]]:
    """(row name, method, head) for every requested method; lln gets one row per head."""
    rows = []
    for m in methods:
        if m == 'lln':
            for h in heads:
                rows.append(('lln' if len(heads) == 1 and not h.label else f'lln[{h.label}]', 'lln', h))
        else:
            rows.append((m, m, None))
    return rows


def parse_methods(text) -> list[str]:
    methods = [m.strip() for m in (text.split(',') if isinstance(text, str) else text) if m.strip()]
    bad = [m for m in methods if m not in ALL_METHODS]
    if bad or not methods:
        raise ValueError(f'unknown method(s) {bad}; choose from {",".join(ALL_METHODS)}')
    return list(dict.fromkeys(methods))


def slug(name: str) -> str:
    return re.sub(r'[^A-Za-z0-9_.-]+', '_', name).strip('_') or 'dataset'
