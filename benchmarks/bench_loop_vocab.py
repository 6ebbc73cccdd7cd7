"""Benchmark: bag-of-binary-words vocabulary training, transform and place-database query.

* Train: random 256-bit descriptors (``--train-n``, default 100k, as 1000 documents of 100),
  k = 10, L = 4, torch (level-batched) vs a numpy per-node reference (DBoW2's recursion, each
  node's k-medians vectorised with numpy) on ``--ref-n`` descriptors (default 20k; the numpy
  reference is slow). A million descriptors is extrapolated linearly (k-medians is O(n·k·iters)
  per level; the level count is fixed).
* Transform: 1 and 16 keyframes of 1000 FAST-like descriptors per call through the trained
  vocabulary, torch vs numpy (same level-by-level descent with a byte-LUT popcount, then
  ``np.unique`` per document).
* Query: database of 2000 keyframes; 1 and 16 queries per call (VINS ``queryL1`` top 4), torch
  inverted file vs a plain Python/numpy inverted file (dict word -> postings, like DBoW2).

Random descriptors are the worst case for a vocabulary (no structure): every k-medians level runs
many iterations. Real BRIEF converges faster.

Prints a markdown table and writes ``benchmarks/results/loop_vocab.json`` (temp file + rename).

Run: ``.venv/bin/python benchmarks/bench_loop_vocab.py [--train-n 100000] [--ref-n 20000] [--threads 1]
[--million]``
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torch_frontend.loop.database import PlaceDatabase  # noqa: E402
from torch_frontend.loop.vocabulary import BowVector, Vocabulary  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json_atomic  # noqa: E402

LUT8 = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def np_hamming(a, b):
    """(..., 4) int64 broadcast -> (...) popcount of xor via a byte LUT."""
    x = np.bitwise_xor(a, b)
    return LUT8[np.ascontiguousarray(x).view(np.uint8)].sum(-1, dtype=np.int64)


# -- numpy reference: DBoW2-style recursion, numpy inside each node -------------------------------
def np_train(x, k, L, rng):
    nodes_parent, nodes_desc = [-1], [np.zeros(4, np.int64)]

    def step(pid, feats, level):
        if len(feats) == 0:
            return
        if len(feats) <= k:
            cents, assign = feats, np.arange(len(feats))
        else:
            cents = [feats[rng.integers(len(feats))]]
            mind = np_hamming(feats, cents[0]).astype(np.float64)
            while len(cents) < k:
                s = mind.sum()
                if s <= 0:
                    break
                cut = rng.uniform(0, s)
                i = min(int(np.searchsorted(np.cumsum(mind), cut)), len(feats) - 1)
                cents.append(feats[i])
                mind = np.minimum(mind, np_hamming(feats, cents[-1]))
            cents = np.stack(cents)
            bits = np.unpackbits(np.ascontiguousarray(feats).view(np.uint8), axis=1, bitorder="little")
            assign = np_hamming(feats[:, None, :], cents[None]).argmin(1)
            while True:
                cnt = np.zeros((len(cents), 256))
                np.add.at(cnt, assign, bits)
                n = np.bincount(assign, minlength=len(cents))
                cents = np.packbits(2 * cnt > n[:, None], axis=1, bitorder="little").view(np.int64)
                new = np_hamming(feats[:, None, :], cents[None]).argmin(1)
                if np.array_equal(new, assign):
                    break
                assign = new
        ids = []
        for c in cents:
            ids.append(len(nodes_parent))
            nodes_parent.append(pid)
            nodes_desc.append(c)
        if level < L:
            for j, cid in enumerate(ids):
                sub = feats[assign == j]
                if len(sub) > 1:
                    step(cid, sub, level + 1)

    step(0, x, 1)
    return np.array(nodes_parent), np.stack(nodes_desc)


def np_transform(children, node_desc, node_word, node_weight, is_leaf, depth, desc):
    """desc (B, K, 4) -> list of dict word -> weight (L1)."""
    B, K, _ = desc.shape
    flat = desc.reshape(-1, 4)
    cur = np.zeros(len(flat), np.int64)
    for _ in range(depth):
        ch = children[cur]
        d = np_hamming(flat[:, None, :], node_desc[np.maximum(ch, 0)])
        d[ch < 0] = 1 << 20
        nxt = ch[np.arange(len(flat)), d.argmin(1)]
        cur = np.where(is_leaf[cur], cur, nxt)
    words = node_word[cur].reshape(B, K)
    wts = node_weight[cur].reshape(B, K)
    out = []
    for b in range(B):
        keep = wts[b] > 0
        u, inv = np.unique(words[b][keep], return_inverse=True)
        v = np.bincount(inv, weights=wts[b][keep], minlength=len(u))
        out.append((u, v / v.sum()))
    return out


class NpDatabase:
    def __init__(self):
        self.inv = {}
        self.n = 0

    def add(self, bow):
        for w, v in zip(*bow):
            self.inv.setdefault(int(w), []).append((self.n, float(v)))
        self.n += 1

    def query(self, bow, max_results=4, max_id=-1):
        s = {}
        last = self.n - 1
        for w, q in zip(*bow):
            for e, d in self.inv.get(int(w), ()):
                if e < max_id or max_id == -1 or e == last:
                    s[e] = s.get(e, 0.0) + abs(q - d) - abs(q) - abs(d)
        r = sorted(s.items(), key=lambda t: t[1])[:max_results]
        return [(e, -v / 2) for e, v in r]


def timeit(fn, repeats):
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts) * 1e3


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--train-n", type=int, default=100_000)
    ap.add_argument("--ref-n", type=int, default=20_000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--million", action="store_true", help="also train on 1e6 descriptors (minutes)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    g = torch.Generator(device=dev).manual_seed(0)
    rows = []

    def rand_desc(*shape):
        return torch.randint(-2**63, 2**63 - 1, (*shape, 4), dtype=torch.int64, generator=g, device=dev)

    # -- train
    k, L = 10, 4
    xr = rand_desc(args.ref_n // 100, 100)
    t = time.perf_counter()
    Vocabulary.train(xr, k=k, L=L, generator=g)
    t_torch_ref = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    np_train(xr.reshape(-1, 4).cpu().numpy(), k, L, np.random.default_rng(0))
    t_np_ref = (time.perf_counter() - t) * 1e3
    rows.append(dict(op=f"train {args.ref_n} desc k={k} L={L}", torch_ms=t_torch_ref, numpy_ms=t_np_ref))
    xt = rand_desc(args.train_n // 100, 100)
    t = time.perf_counter()
    voc = Vocabulary.train(xt, k=k, L=L, generator=g)
    t_train = (time.perf_counter() - t) * 1e3
    rows.append(dict(op=f"train {args.train_n} desc k={k} L={L}", torch_ms=t_train, numpy_ms=None))
    extrap = t_train * 1_000_000 / args.train_n
    rows.append(dict(op=f"train 1e6 desc k={k} L={L} (extrapolated, linear)", torch_ms=extrap, numpy_ms=None))
    if args.million:
        xm = rand_desc(10_000, 100)
        t = time.perf_counter()
        Vocabulary.train(xm, k=k, L=L, generator=g)
        rows.append(dict(op=f"train 1e6 desc k={k} L={L} (measured)", torch_ms=(time.perf_counter() - t) * 1e3,
                         numpy_ms=None))
        del xm

    # -- transform
    npv = [a.cpu().numpy() for a in (voc.children, voc.node_desc, voc.node_word, voc.node_weight, voc.is_leaf)]
    for B in (1, 16):
        q = rand_desc(B, 1000)
        qn = q.cpu().numpy()
        tt = timeit(lambda q=q: voc.transform(q), args.repeats)
        tn = timeit(lambda qn=qn: np_transform(*npv, voc.depth, qn), max(1, args.repeats // 2))
        rows.append(dict(op=f"transform {B} x 1000 desc", torch_ms=tt, numpy_ms=tn))

    # -- query
    NE = 2000
    bows = voc.transform(rand_desc(NE + 16, 300))
    db = PlaceDatabase(voc, device=dev)
    ndb = NpDatabase()
    tadd = time.perf_counter()
    for i in range(NE):
        db.add(BowVector(bows.words[i:i + 1], bows.weights[i:i + 1]))
    tadd = (time.perf_counter() - tadd) * 1e3 / NE
    hb = [(w[w >= 0].cpu().numpy(), v[w >= 0].cpu().numpy()) for w, v in zip(bows.words, bows.weights)]
    t = time.perf_counter()
    for i in range(NE):
        ndb.add(hb[i])
    nadd = (time.perf_counter() - t) * 1e3 / NE
    rows.append(dict(op=f"db add (per keyframe, {NE} entries)", torch_ms=tadd, numpy_ms=nadd))
    for B in (1, 16):
        qb = BowVector(bows.words[NE:NE + B], bows.weights[NE:NE + B])
        tt = timeit(lambda qb=qb: db.query_many(qb, 4, NE - 50), args.repeats)
        tn = timeit(lambda B=B: [ndb.query(hb[NE + i], 4, NE - 50) for i in range(B)], args.repeats)
        rows.append(dict(op=f"query {B} keyframe(s), {NE} entries", torch_ms=tt, numpy_ms=tn))
    # consistency check of the two databases on the last query batch
    ids, sc = db.query_many(BowVector(bows.words[NE:NE + 16], bows.weights[NE:NE + 16]), 4, NE - 50)
    for i in range(16):
        ref = ndb.query(hb[NE + i], 4, NE - 50)
        assert [e for e, _ in ref] == [e for e in ids[i].tolist() if e >= 0][:len(ref)]

    print(f"\n### Loop vocabulary benchmark ({dev}, {args.threads} thread(s), torch {torch.__version__})\n")
    print("| operation | torch ms | numpy ref ms | speed-up |")
    print("|---|---:|---:|---:|")
    for r in rows:
        n, t = r["numpy_ms"], r["torch_ms"]
        ns = "" if n is None else f"{n:.1f}"
        sp = "" if n is None else f"{n / t:.1f}x"
        print(f"| {r['op']} | {t:.1f} | {ns} | {sp} |")
    out = dict(device=str(dev), threads=args.threads, torch=torch.__version__, platform=platform.platform(),
               rows=rows, vocabulary=dict(nodes=voc.num_nodes, words=voc.num_words, k=k, L=L))
    res = REPO / "benchmarks" / "results"
    res.mkdir(parents=True, exist_ok=True)
    write_json_atomic(res / "loop_vocab.json", out)


if __name__ == "__main__":
    main()
