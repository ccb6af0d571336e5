"""Training the LLN head with image-level labels only (Xin et al., ICRA 2019, Sec. III-B).

Two objectives, both on tuples of 1 query, its positives and K hard negatives re-mined with the
current head every epoch:

`triplet` (the paper's):
    embedding  F = normalize( sum_ij w_ij * f_ij )     w = LLN activation, f_ij = L2-normalised features
    loss       sum_k max(0, |F_q - F_p| + m - |F_q - F_nk|)       m = 0.3

`rerank` (ours, the default): train the head on the score it is used for. At test time the head only
picks the top-n cells, and S = sum w_ij s_ij over the mutual matches of the picked cells reranks the
holistic top-K. The backbone is frozen, so the mutual matches of ALL cells between a query and each
of its candidates, their cosines s_ij and offset weights w_ij are fixed tables; the head decides a
soft top-n membership of every cell, a_i = sigmoid((z_i - z_(n)) / T) (z = logits, z_(n) the n-th
largest, held constant), and
    S~(q, c)   = sum_i a_i(q) * a_j(i)(c) * w_ij * s_ij / n         over query cells i, j(i) = partner
    loss       = -log( sum_pos exp(S~/tau) / sum_{pos, negs} exp(S~/tau) )
Candidates are what the test sees: the holistic top-K (prefilter_k) plus the positives.

The backbone is frozen, so its feature maps come from a FeatureCache and an epoch costs only the
head. Training data is a `PairSet` (training_pairs.py): query and reference images with boolean positive / negative
masks, made from any evaluation dataset (aligned traverses, VPR-Bench, loop and pose sequences),
place-labelled folders or the Retrieval-SfM-120k pickle, and combinable. Images of different
shapes (Nordland 18x9 cells, 4:3 sequences 12x9, square thumbnails 9x9) train together: feature
maps are padded at the right and bottom to one grid as the head's convs pad (zeros, or the last row
and column repeated), which leaves the head's logits of the real cells unchanged, and padded cells
are never selected or matched. crop_views adds lateral crops of the queries (lateral_crops).

Validation is a list of evaluation datasets; the kept head (best.pt) is the one with the best MEAN
P@100%R over them, so no single set decides (the per-set figures are in history.json).
"""

from __future__ import annotations

import copy
import json
import os
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..errors import DatasetError
from ..io.datasets import image_keys
from ..io.features import FeatureCache
from . import metrics
from .landmarks import l2_normalize, stack_landmarks
from .lln import LLNHead, embed, save_checkpoint
from .retrieval import rank_all
from .training_objectives import match_tables, rerank_loss, soft_selection, soft_similarity, triplet_loss
from .training_pairs import PairSet

default_conf = {
    'objective': 'rerank',  # rerank (train on the test-time score) | triplet (the paper's loss)
    'epochs': 10,
    'lr': 1e-3,  # the paper's 1e-6 (TensorFlow, SfM-120k) barely moves this head: see docs
    'batch_size': 10,  # tuples per optimiser step
    'negatives': 4,  # hard negatives per tuple (K)
    'margin': 0.3,
    'tuples_per_epoch': 1000,  # queries drawn (without replacement) per epoch; 0 = all
    # True: every --data set gives the same share of an epoch's queries (a small set's are drawn
    # again), so a 2,145-place route does not outweigh three sets of ~200 (docs/generalisation.md)
    'balance_sets': False,
    'train_size': 288,  # input height, aspect kept (as at test time); (W, H) squashes (paper: 352x352)
    'neg_margin': 10,  # route data: refs within this many frames of a positive are not negatives
    'seed': 0,
    'head': {},  # LLNHead conf overrides
    'val_top_n': 50,
    'val_prefilter_k': 30,  # also the rerank objective's holistic candidates per query
    'tau': 0.05,  # rerank: softmax temperature on S~ (S~ is in [0, 1])
    'soft_temp': 1.0,  # rerank: width T of the soft top-n membership, in logit units
    # lateral crops: every usable query also trains as this many copies of its feature map cut to a
    # random window of crop_range x its width (full height, at a random place), with the same
    # positives and negatives. A place's discriminative part is then not always where the full view
    # has it, so the head cannot learn a fixed centre prior (docs/generalisation.md, issue 28)
    'crop_views': 0,
    'crop_range': (0.5, 0.9),
}
PAD_LOGIT = -1e4  # logit of a padded (not real) cell: never in the soft top-n
OBJECTIVES = ('rerank', 'triplet')


def pad_stack(feats: list, grid: tuple | None = None, mode: str = 'zeros') -> tuple[torch.Tensor, np.ndarray]:
    """Feature maps of any grid, list of (D, h_i, w_i) -> (M, D, H, W) padded at the right and bottom
    to grid (H, W) (default: the largest), and valid (M, H*W) bool: which flat cells are real.

    mode is the head's padding: 'zeros' fills with 0, 'replicate' repeats the last row and column,
    so the head's convs see at a real cell what they see on that image alone either way."""
    d = feats[0].shape[0]
    h, w = grid or (max(f.shape[1] for f in feats), max(f.shape[2] for f in feats))
    out = np.empty((len(feats), d, h, w), feats[0].dtype)
    valid = np.zeros((len(feats), h, w), bool)
    for i, f in enumerate(feats):
        pad = ((0, 0), (0, h - f.shape[1]), (0, w - f.shape[2]))
        out[i] = np.pad(f, pad, mode='edge' if mode == 'replicate' else 'constant')
        valid[i, : f.shape[1], : f.shape[2]] = True
    return torch.from_numpy(out), valid.reshape(len(feats), h * w)


def lateral_crops(
    feats: list, queries: np.ndarray, views: int, crop_range: tuple, rng: np.random.Generator
) -> tuple[list, np.ndarray]:
    """`views` random lateral crops of every query's feature map.

    feats: list of (D, h, w); queries (U,) indices into it. Each crop keeps the full height and a
    window of u x w columns, u ~ U(crop_range), at a uniform random offset. Returns the crops (a list
    of (D, h, w'), U * views of them) and (U * views,) the index of the query each came from."""
    lo, hi = (float(v) for v in crop_range)
    if not 0 < lo <= hi <= 1:
        raise DatasetError(f'crop_range must satisfy 0 < lo <= hi <= 1, got {crop_range}')
    crops, origin = [], []
    for q in queries:
        f = feats[int(q)]
        w = f.shape[2]
        for _ in range(int(views)):
            cw = min(w, max(1, int(round(rng.uniform(lo, hi) * w))))
            x0 = int(rng.integers(0, w - cw + 1))
            crops.append(np.ascontiguousarray(f[:, :, x0 : x0 + cw]))
            origin.append(int(q))
    return crops, np.array(origin, np.int64)


class Trainer:
    """Train a head on a PairSet, validating on evaluation Datasets every epoch.

    val: a Dataset, a list of them, or None. out_dir holds last.pt (everything needed to resume:
    head, optimiser, epoch, RNG state, history) and best.pt (the head with the best mean validation
    precision at 100% recall over the val sets, as an lln_ros checkpoint).
    """

    def __init__(
        self,
        extractor,
        pairs: PairSet,
        val=None,
        conf: dict | None = None,
        cache_dir: str = 'cache/features',
        out_dir: str = 'out/train',
        meta: dict | None = None,
    ):
        self.conf = conf = {**default_conf, **(conf or {})}
        self.extractor = extractor
        self.pairs = pairs
        self.vals = [] if val is None else list(val) if isinstance(val, (list, tuple)) else [val]
        self.val = self.vals or None  # truthiness: is there any validation
        names = [v.name for v in self.vals]
        if len(set(names)) != len(names):
            raise DatasetError(f'validation datasets need distinct names (their scores are kept by name), got {names}')
        self.out = Path(out_dir)
        self.meta = meta or {}
        # the images this head sees, for every best.pt it writes (lln-eval's held-out status)
        self.seen_images = {
            'train': image_keys(pairs.query_paths + pairs.ref_paths),
            'val': image_keys([p for v in self.vals for p in (*v.query_paths, *v.ref_paths)]),
        }
        self.cache = FeatureCache(cache_dir, extractor)
        if conf['objective'] not in OBJECTIVES:
            raise DatasetError(f'unknown objective {conf["objective"]!r}; choose one of {OBJECTIVES}')
        self.queries = pairs.usable()
        if not len(self.queries):
            raise DatasetError(f'{pairs.name}: no query has both a positive and a negative')
        torch.manual_seed(conf['seed'])
        self.head = LLNHead(extractor.backbone.dim, {**conf['head'], 'seed': conf['seed']})
        self.optimizer = torch.optim.Adam(self.head.parameters(), lr=conf['lr'])
        self.rng = np.random.default_rng(conf['seed'])
        self.epoch = 0
        self.history: list[dict] = []
        self.best = -1.0

    # ------------------------------------------------------------------ data

    def load_features(self):
        size = self.conf['train_size']
        size = size if isinstance(size, int) else tuple(size)
        q = self.cache.load(self.pairs.query_paths, size, progress='train features (queries)')
        r = (
            q
            if self.pairs.ref_paths is self.pairs.query_paths
            else self.cache.load(self.pairs.ref_paths, size, progress='train features (refs)')
        )
        if self.conf['crop_views']:
            q = self._add_lateral_crops(q)
        # one grid for queries and refs (the triplet step batches them together)
        grid = (max(f.shape[1] for f in q + r), max(f.shape[2] for f in q + r))
        mode = self.head.conf['padding']
        self.fq, self.q_valid = pad_stack(q, grid, mode)
        self.fr, self.r_valid = (self.fq, self.q_valid) if r is q else pad_stack(r, grid, mode)
        h = int(self.extractor.conf['input_height'])
        self.val_feats = [
            (
                self.cache.load(v.query_paths, h, progress=f'val features {v.name} (queries)'),
                self.cache.load(v.ref_paths, h, progress=f'val features {v.name} (refs)'),
            )
            for v in self.vals
        ]

    def _add_lateral_crops(self, q: list) -> list:
        """q + lateral crops of every usable query (lateral_crops); the crops become queries of
        their own with their original's positives and negatives, and join self.queries."""
        # a generator of its own: the epochs' query draws are the same with and without crops
        rng = np.random.default_rng(int(self.conf['seed']) + 1)
        crops, origin = lateral_crops(q, self.queries, self.conf['crop_views'], self.conf['crop_range'], rng)
        p = self.pairs
        self.pairs = PairSet(
            f'{p.name}+crops',
            list(p.query_paths) + [f'{p.query_paths[o]}#crop{i}' for i, o in enumerate(origin)],
            p.ref_paths if p.ref_paths is not p.query_paths else list(p.ref_paths),
            np.concatenate([p.positive, p.positive[origin]]),
            np.concatenate([p.negative, p.negative[origin]]),
            None if p.source is None else np.concatenate([p.source, p.source[origin]]),
        )
        self.queries = np.concatenate([self.queries, len(q) + np.arange(len(crops))])
        return list(q) + crops

    @torch.no_grad()
    def embed_all(self, feats: torch.Tensor, batch: int = 256) -> torch.Tensor:
        self.head.eval()
        return torch.cat([embed(self.head, feats[i : i + batch].float()) for i in range(0, len(feats), batch)])

    # ------------------------------------------------------------------ loop

    def choose_queries(self) -> np.ndarray:
        """This epoch's queries: `tuples_per_epoch` of the usable ones (0 = as many as there are), at
        random; with balance_sets, the same number from every source set, each set's queries without
        replacement until they run out and then again (in a new order)."""
        n = self.conf['tuples_per_epoch'] or len(self.queries)
        source = self.pairs.source
        if not self.conf['balance_sets'] or source is None:
            return self.rng.permutation(self.queries)[:n]
        groups = [self.queries[source[self.queries] == s] for s in np.unique(source[self.queries])]
        share = -(-n // len(groups))  # ceil: every set gets its full share
        picks = []
        for g in groups:
            rounds = -(-share // len(g))
            picks.append(np.concatenate([self.rng.permutation(g) for _ in range(rounds)])[:share])
        return self.rng.permutation(np.concatenate(picks))[:n]

    def mine(self) -> np.ndarray:
        """This epoch's tuples under the current head (see mine_triplets / mine_rerank)."""
        chosen = self.choose_queries()
        return self.mine_rerank(chosen) if self.conf['objective'] == 'rerank' else self.mine_triplets(chosen)

    def train_epoch(self, tuples: np.ndarray) -> float:
        step = self.rerank_step if self.conf['objective'] == 'rerank' else self.triplet_step
        self.head.train()
        losses = []
        bs = self.conf['batch_size']
        for start in tqdm(range(0, len(tuples), bs), desc=f'epoch {self.epoch + 1}', leave=False, unit='batch'):
            loss = step(tuples[start : start + bs])
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
            losses.append(loss.item())
        return float(np.mean(losses))

    # ------------------------------------------------------------------ triplet objective

    def mine_triplets(self, chosen: np.ndarray) -> np.ndarray:
        """(T, 2 + K) tuples of indices: a query, its most similar positive ref,
        and its K most similar negatives, under the current head."""
        k = self.conf['negatives']
        eq = self.embed_all(self.fq[chosen])
        er = self.embed_all(self.fr)
        sims = (eq @ er.T).numpy()  # (T, R)
        pos = np.where(self.pairs.positive[chosen], sims, -np.inf).argmax(1)
        neg_s = np.where(self.pairs.negative[chosen], sims, -np.inf)
        negs = np.argsort(-neg_s, axis=1, kind='stable')[:, :k]
        # a query with fewer than K negatives repeats its hardest one
        short = ~np.isfinite(np.take_along_axis(neg_s, negs, 1))
        negs[short] = np.broadcast_to(negs[:, :1], negs.shape)[short]
        return np.concatenate([chosen[:, None], pos[:, None], negs], axis=1)

    def triplet_step(self, t: np.ndarray) -> torch.Tensor:
        k = self.conf['negatives']
        feats = torch.cat([self.fq[t[:, 0]], self.fr[t[:, 1]], self.fr[t[:, 2:].ravel()]]).float()
        e = embed(self.head, feats)
        b = len(t)
        return triplet_loss(e[:b], e[b : 2 * b], e[2 * b :].view(b, k, -1), self.conf['margin'])

    # ------------------------------------------------------------------ rerank objective

    def prepare_rerank(self) -> None:
        """Candidates and match tables of every usable query, once (they do not depend on the head):
        cand (U, C) ref indices, positives first, -1 padding; n_pos (U,); partner, value (U, C, N)."""
        d, h, w = self.fq.shape[1:]

        def local(f):  # (M, D, h, w) -> (M, N, D) L2-normalised cells (padded cells stay 0)
            x = f.float().numpy().reshape(len(f), d, h * w).transpose(0, 2, 1)
            return l2_normalize(x)

        def holistic(f, valid):  # the extractor's global descriptor: max pool over real cells, L2-normalised
            x = f.float().numpy().reshape(len(f), d, h * w)
            return l2_normalize(np.where(valid[:, None], x, -np.inf).max(2))

        qv = self.q_valid[self.queries]
        lq, lr = local(self.fq[self.queries]), local(self.fr)
        hol = holistic(self.fq[self.queries], qv) @ holistic(self.fr, self.r_valid).T  # (U, R)
        cells = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2)
        k = int(self.conf['val_prefilter_k'])
        rows = []
        for u, q in enumerate(tqdm(self.queries, desc='match tables', leave=False, unit='query')):
            top = np.argsort(-hol[u], kind='stable')[:k]
            cand = np.concatenate([np.flatnonzero(self.pairs.positive[q]), top[self.pairs.negative[q, top]]])
            rows.append(
                (cand, int(self.pairs.positive[q].sum()))
                + match_tables(lq[u], lr[cand], cells, valid_q=qv[u], valid_c=self.r_valid[cand])
            )
        c = max(len(r[0]) for r in rows)
        u, n = len(rows), h * w
        self.rr_cand = np.full((u, c), -1, np.int64)
        self.rr_partner = np.zeros((u, c, n), np.int16)
        self.rr_value = np.zeros((u, c, n), np.float32)
        self.rr_npos = np.array([r[1] for r in rows])
        for i, (cand, _, partner, value) in enumerate(rows):
            self.rr_cand[i, : len(cand)], self.rr_partner[i, : len(cand)], self.rr_value[i, : len(cand)] = (
                cand,
                partner,
                value,
            )
        self.rr_row = {int(q): i for i, q in enumerate(self.queries)}

    def _logits(self, feats: torch.Tensor, valid: np.ndarray) -> torch.Tensor:
        """(B, N) head logits, PAD_LOGIT at padded cells."""
        return self.head.logits(feats.float()).flatten(1).masked_fill(~torch.from_numpy(valid), PAD_LOGIT)

    def soft_scores(self, rows: np.ndarray, cols: np.ndarray) -> torch.Tensor:
        """S~ (B, C') of query rows (B,) against their candidate columns cols (B, C') (-1 = none)."""
        n, temp = int(self.conf['val_top_n']), float(self.conf['soft_temp'])
        cand = np.where(cols >= 0, np.take_along_axis(self.rr_cand[rows], np.maximum(cols, 0), 1), 0)
        refs, inv = np.unique(cand, return_inverse=True)
        q = self.queries[rows]
        a_q = soft_selection(self._logits(self.fq[q], self.q_valid[q]), n, temp)
        a_r = soft_selection(self._logits(self.fr[refs], self.r_valid[refs]), n, temp)
        a_c = a_r[torch.from_numpy(inv.reshape(cand.shape))]  # (B, C', N)
        pick = (rows[:, None], np.maximum(cols, 0))
        partner = torch.from_numpy(self.rr_partner[pick].astype(np.int64))
        return soft_similarity(a_q, a_c, partner, torch.from_numpy(self.rr_value[pick]), n)

    @torch.no_grad()
    def mine_rerank(self, chosen: np.ndarray, batch: int = 64) -> np.ndarray:
        """(T, 1 + P + K) rows: the query's table row, then candidate columns: its positives, then the
        K negatives with the highest S~ under the current head, then -1 pads (P = most positives)."""
        self.head.eval()
        k, p = self.conf['negatives'], int(self.rr_npos.max())
        rows = np.array([self.rr_row[int(q)] for q in chosen])
        out = np.full((len(rows), 1 + p + k), -1, np.int64)
        out[:, 0] = rows
        cols_all = np.arange(self.rr_cand.shape[1])
        for start in range(0, len(rows), batch):
            r = rows[start : start + batch]
            cols = np.where(self.rr_cand[r] >= 0, cols_all[None], -1)
            s = self.soft_scores(r, cols).numpy()
            for j, row in enumerate(r):
                npos, valid = self.rr_npos[row], cols[j] >= 0
                neg = np.flatnonzero(valid & (cols_all >= npos))
                hard = neg[np.argsort(-s[j, neg], kind='stable')[:k]]
                out[start + j, 1 : 1 + npos] = cols_all[:npos]
                out[start + j, 1 + npos : 1 + npos + len(hard)] = hard
        return out

    def rerank_step(self, t: np.ndarray) -> torch.Tensor:
        rows, cols = t[:, 0], t[:, 1:]  # mine_rerank packs the positives first, as the loss needs
        scores = self.soft_scores(rows, cols)
        n_pos = torch.from_numpy(self.rr_npos[rows])
        return rerank_loss(scores, n_pos, torch.from_numpy(cols >= 0), float(self.conf['tau']))

    @torch.no_grad()
    def validate(self) -> tuple[float, dict]:
        """(mean, {val set name: P@100%R}) of the LLN rerank on every validation dataset."""
        if not self.vals:
            return float('nan'), {}
        self.head.eval()
        ex = copy.copy(self.extractor)
        ex.head = self.head
        ex.conf = {**self.extractor.conf, 'method': 'lln', 'top_n': self.conf['val_top_n']}
        per_set = {}
        for v, (fq, fr) in zip(self.vals, self.val_feats):
            qs = [ex.from_features(f, s) for f, s in zip(fq, v.info.get('query_sizes'))]
            rs = stack_landmarks([ex.from_features(f, s) for f, s in zip(fr, v.info.get('ref_sizes'))])
            ranked, _ = rank_all(qs, rs, self.conf['val_prefilter_k'], allowed=v.candidates)
            per_set[v.name] = metrics.p_at_100r(ranked, v.gt)
        return float(np.mean(list(per_set.values()))), per_set

    def fit(self, resume: bool = True) -> dict:
        self.out.mkdir(parents=True, exist_ok=True)
        if resume and (self.out / 'last.pt').is_file():
            self._restore(self.out / 'last.pt')
        self.load_features()
        if self.conf['objective'] == 'rerank':
            self.prepare_rerank()
        if self.epoch == 0 and self.val is not None:
            untrained, per_set = self.validate()
            self.history.append({'epoch': 0, 'val_p_at_100r': untrained, 'val_per_set': per_set})
            print(f'epoch 0 (untrained head): val P@100R {untrained:.3f} {_fmt(per_set)}', flush=True)
            # the untrained head competes too: a head that training only makes worse on the
            # validation sets is not kept (with norm_prior > 0 the untrained head is ACT's selection)
            self.best = untrained
            self._save_best(per_set)
        while self.epoch < self.conf['epochs']:
            t0 = time.perf_counter()
            tuples = self.mine()
            loss = self.train_epoch(tuples)
            self.epoch += 1
            score, per_set = self.validate()
            row = {
                'epoch': self.epoch,
                'loss': loss,
                'val_p_at_100r': score,
                'val_per_set': per_set,
                'seconds': time.perf_counter() - t0,
            }
            self.history.append(row)
            improved = self.val is None or score > self.best
            if improved:
                self.best = score if self.val is not None else self.best
                self._save_best(per_set)
            self._save_last()  # after best.pt: an interruption never leaves last ahead of best
            print(
                f'epoch {self.epoch}: loss {loss:.4f}, val P@100R {score:.3f} {_fmt(per_set)}'
                f'{" (best)" if improved else ""}, {row["seconds"]:.0f} s',
                flush=True,
            )
        return {'best_val_p_at_100r': self.best, 'history': self.history}

    # ------------------------------------------------------------------ files

    def _save_best(self, per_set: dict | None = None) -> None:
        bb = self.extractor.conf['backbone']
        save_checkpoint(
            str(self.out / 'best.pt'),
            self.head,
            bb['name'],
            self.extractor.backbone.layer,
            trained=self.epoch > 0,
            epoch=self.epoch,
            val_p_at_100r=self.best,
            train_conf=_jsonable(self.conf),
            train_data=self.pairs.name,
            val_data=[v.name for v in self.vals] or None,
            val_per_set=per_set or {},
            seen_images=self.seen_images,
            **self.meta,
        )

    def _save_last(self) -> None:
        state = {
            'head': self.head.state_dict(),
            'optimizer': self.optimizer.state_dict(),
            'epoch': self.epoch,
            'rng': self.rng.bit_generator.state,
            'torch_rng': torch.get_rng_state(),
            'history': self.history,
            'best': self.best,
            'conf': _jsonable(self.conf),
        }
        tmp = self.out / 'last.pt.tmp'
        torch.save(state, tmp)
        os.replace(tmp, self.out / 'last.pt')
        (self.out / 'history.json').write_text(json.dumps(self.history, indent=1))

    def _restore(self, path: Path) -> None:
        state = torch.load(path, map_location='cpu', weights_only=False)
        # only the number of epochs may change on resume (to extend a run)
        same = {k: v for k, v in state['conf'].items() if k != 'epochs'} == {
            k: v for k, v in _jsonable(self.conf).items() if k != 'epochs'
        }
        if not same:
            raise DatasetError(
                f'{path} was written with another training configuration; use a new --out '
                f'or remove it (was {state["conf"]}, now {_jsonable(self.conf)})'
            )
        self.head.load_state_dict(state['head'])
        self.optimizer.load_state_dict(state['optimizer'])
        self.epoch, self.history, self.best = state['epoch'], state['history'], state['best']
        self.rng.bit_generator.state = state['rng']
        torch.set_rng_state(state['torch_rng'])
        print(f'resuming from {path} after epoch {self.epoch}', flush=True)


def _fmt(per_set: dict) -> str:
    return '(' + ', '.join(f'{k} {v:.3f}' for k, v in per_set.items()) + ')' if len(per_set) > 1 else ''


def _jsonable(conf: dict) -> dict:
    return json.loads(json.dumps(conf, default=list))
