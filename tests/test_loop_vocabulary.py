"""Bag of binary words: transform vs a plain recursive reference, training, file formats."""

from __future__ import annotations

import math
import random
import struct

import numpy as np
import pytest
import torch

from torch_frontend.loop.vocabulary import (
    BINARY,
    IDF,
    L1_NORM,
    TF_IDF,
    Vocabulary,
    _hamming_packed,
    _pack_bits,
    _unpack_bits,
    bow_to_dense,
)

M64 = (1 << 64) - 1


@pytest.fixture(autouse=True)
def _one_thread():
    # The CI box has 2 busy cores: small int kernels run far slower with intra-op threads.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def to_int(words) -> int:
    return sum((int(w) & M64) << (64 * j) for j, w in enumerate(words))


def to_words(v: int):
    out = []
    for j in range(4):
        w = (v >> (64 * j)) & M64
        out.append(w - (1 << 64) if w >= 1 << 63 else w)
    return out


def rand_desc(rng: random.Random) -> int:
    return rng.getrandbits(256)


def make_tree(seed: int, depth: int = 3, max_children: int = 4, pool: int = 6):
    """Random tree as file-style records (nid, pid, weight, desc int) in a shuffled record order.

    Sibling descriptors come from a small pool so that distance ties (first child wins) happen.
    """
    rng = random.Random(seed)
    base = [rand_desc(rng) for _ in range(pool)]
    recs = []
    frontier = [(0, 0)]
    nid = 1
    while frontier:
        node, lev = frontier.pop()
        nch = rng.randint(1, max_children) if lev < depth and (lev == 0 or rng.random() < 0.8) else 0
        for _ in range(nch):
            d = base[rng.randrange(pool)] ^ (rng.getrandbits(256) & rng.getrandbits(256) & rng.getrandbits(256)
                                             if rng.random() < 0.5 else 0)
            recs.append([nid, node, 0.0, d])
            frontier.append((nid, lev + 1))
            nid += 1
    rng.shuffle(recs)  # children order = record order (per parent)
    parents = {r[1] for r in recs}
    leaves = [r for r in recs if r[0] not in parents]
    word_ids = list(range(len(leaves)))
    rng.shuffle(word_ids)
    words = []
    for r, w in zip(leaves, word_ids):
        r[2] = 0.0 if rng.random() < 0.15 else rng.uniform(0.1, 3.0)  # some stop words
        words.append((w, r[0]))
    return recs, words, base


def ref_tree(recs, words):
    children = {0: []}
    desc, weight = {}, {}
    for nid, pid, w, d in recs:
        children.setdefault(pid, []).append(nid)
        children.setdefault(nid, [])
        desc[nid], weight[nid] = d, w
    word_of = {n: w for w, n in words}
    return children, desc, weight, word_of


def ref_word(tree, d: int):
    children, desc, weight, word_of = tree
    n = 0
    while children[n]:
        best, bd = None, None
        for c in children[n]:
            dist = bin(d ^ desc[c]).count("1")
            if bd is None or dist < bd:  # strict: first child wins ties
                best, bd = c, dist
        n = best
    return word_of[n], weight[n]


def ref_bow(tree, docs, weighting=TF_IDF):
    out = []
    for doc in docs:
        v = {}
        for d in doc:
            w, wt = ref_word(tree, d)
            if wt <= 0:
                continue
            if weighting in (IDF, BINARY):
                v.setdefault(w, wt)
            else:
                v[w] = v.get(w, 0.0) + wt
        s = sum(abs(x) for x in v.values())
        out.append({w: x / s for w, x in v.items()} if s > 0 else {})
    return out


def vocab_from_records(recs, words, weighting=TF_IDF):
    M = len(recs) + 1
    parent = np.full(M, -1)
    nd = np.zeros((M, 4), np.int64)
    nw = np.zeros(M)
    for nid, pid, w, d in recs:
        parent[nid] = pid
        nd[nid] = to_words(d)
        nw[nid] = w
    node_word = np.full(M, -1)
    for w, n in words:
        node_word[n] = w
    return Vocabulary(10, 3, parent, torch.from_numpy(nd), torch.from_numpy(nw), node_word,
                      L1_NORM, weighting, order=[0] + [r[0] for r in recs])


def sample_docs(base, rng, B=5, K=40):
    docs = [[base[rng.randrange(len(base))] ^ (rng.getrandbits(256) & rng.getrandbits(256) & rng.getrandbits(256))
             if rng.random() < 0.7 else rand_desc(rng) for _ in range(K)] for _ in range(B)]
    t = torch.tensor([[to_words(d) for d in doc] for doc in docs], dtype=torch.int64)
    return docs, t


def assert_bow_equal(bow, ref, atol=1e-12):
    words, weights = bow
    for b, r in enumerate(ref):
        got = {int(w): float(x) for w, x in zip(words[b].tolist(), weights[b].tolist()) if w >= 0}
        assert got.keys() == r.keys()
        for w in r:
            assert abs(got[w] - r[w]) <= atol
        ids = [w for w in words[b].tolist() if w >= 0]
        assert ids == sorted(ids)
        n = len(ids)
        assert (words[b, n:] == -1).all() and (weights[b, n:] == 0).all()


def test_bit_helpers():
    rng = random.Random(0)
    a = [rand_desc(rng) for _ in range(50)]
    b = [rand_desc(rng) for _ in range(50)]
    ta = torch.tensor([to_words(x) for x in a])
    tb = torch.tensor([to_words(x) for x in b])
    assert _hamming_packed(ta, tb).tolist() == [bin(x ^ y).count("1") for x, y in zip(a, b)]
    bits = _unpack_bits(ta)
    assert bits.shape == (50, 256)
    assert bits[3].tolist() == [(a[3] >> i) & 1 for i in range(256)]
    assert torch.equal(_pack_bits(bits), ta)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_transform_matches_recursive_reference(seed, device):
    recs, words, base = make_tree(seed)
    tree = ref_tree(recs, words)
    voc = vocab_from_records(recs, words).to(device)
    rng = random.Random(100 + seed)
    docs, t = sample_docs(base, rng)
    valid = torch.rand(t.shape[:2], generator=torch.Generator().manual_seed(seed)) > 0.2
    w, wt = voc.transform_words(t.to(device), valid.to(device))
    for b, doc in enumerate(docs):
        for i, d in enumerate(doc):
            if valid[b, i]:
                rw, rwt = ref_word(tree, d)
                assert (int(w[b, i]), float(wt[b, i])) == (rw, rwt)
            else:
                assert int(w[b, i]) == -1 and float(wt[b, i]) == 0
    docs_v = [[d for d, ok in zip(doc, valid[b].tolist()) if ok] for b, doc in enumerate(docs)]
    bow = voc.transform(t.to(device), valid.to(device))
    assert bow.words.device.type == torch.device(device).type
    assert_bow_equal([x.cpu() for x in bow], ref_bow(tree, docs_v))
    dense = bow_to_dense(bow, voc.num_words)
    assert torch.allclose(dense.sum(1)[dense.sum(1) > 0].cpu(), torch.ones(1, dtype=torch.float64))


def test_transform_idf_weighting_keeps_one_copy():
    recs, words, base = make_tree(5)
    tree = ref_tree(recs, words)
    voc = vocab_from_records(recs, words, weighting=IDF)
    docs, t = sample_docs(base, random.Random(7), B=3, K=30)
    assert_bow_equal(voc.transform(t), ref_bow(tree, docs, weighting=IDF))


def write_vins_bin(path, recs, words, k=10, L=3, count_root=False):
    with open(path, "wb") as f:
        f.write(struct.pack("<6i", k, L, 0, 0, len(recs) + (1 if count_root else 0), len(words)))
        for nid, pid, w, d in recs:
            f.write(struct.pack("<iid4Q", nid, pid, w, *[(d >> (64 * j)) & M64 for j in range(4)]))
        for w, n in words:
            f.write(struct.pack("<ii", n, w))


@pytest.mark.parametrize("count_root", [False, True])
def test_load_vins_bin(tmp_path, count_root):
    recs, words, base = make_tree(3)
    tree = ref_tree(recs, words)
    p = tmp_path / "voc.bin"
    write_vins_bin(p, recs, words, count_root=count_root)
    voc = Vocabulary.load_vins_bin(p)
    assert (voc.k, voc.L, voc.scoring, voc.weighting) == (10, 3, 0, 0)
    assert voc.num_words == len(words)
    docs, t = sample_docs(base, random.Random(11))
    assert_bow_equal(voc.transform(t), ref_bow(tree, docs))
    # Our writer produces the same layout and round-trips.
    voc.save_vins_bin(tmp_path / "again.bin")
    voc2 = Vocabulary.load_vins_bin(tmp_path / "again.bin")
    b1, b2 = voc.transform(t), voc2.transform(t)
    assert torch.equal(b1.words, b2.words) and torch.equal(b1.weights, b2.weights)


def test_load_vins_bin_rejects_bad_size(tmp_path):
    from torch_frontend.errors import ConfigError

    recs, words, _ = make_tree(3)
    p = tmp_path / "voc.bin"
    write_vins_bin(p, recs, words)
    p.write_bytes(p.read_bytes()[:-3])
    with pytest.raises(ConfigError):
        Vocabulary.load_vins_bin(p)


@pytest.mark.parametrize("style", ["bytes", "bitset"])
def test_load_dbow2_yaml(tmp_path, style):
    recs, words, base = make_tree(4)
    tree = ref_tree(recs, words)
    lines = ["%YAML:1.0", "---", "vocabulary:", "   k: 10", "   L: 3", "   scoringType: 0",
             "   weightingType: 0", "   nodes:"]
    for nid, pid, w, d in recs:
        if style == "bytes":
            s = " ".join(str((d >> (8 * j)) & 0xFF) for j in range(32)) + " "
        else:
            s = "".join(str((d >> i) & 1) for i in range(255, -1, -1))
        lines.append(f'      - {{ nodeId:{nid}, parentId:{pid}, weight:{w!r}, descriptor:"{s}" }}')
    lines.append("   words:")
    lines += [f"      - {{ wordId:{w}, nodeId:{n} }}" for w, n in words]
    p = tmp_path / "voc.yml"
    p.write_text("\n".join(lines) + "\n")
    voc = Vocabulary.load_dbow2_yaml(p)
    assert (voc.k, voc.L) == (10, 3)
    docs, t = sample_docs(base, random.Random(12))
    assert_bow_equal(voc.transform(t), ref_bow(tree, docs))


def _train_small(seed=0, D=12, K=25, k=3, L=3):
    g = torch.Generator().manual_seed(seed)
    # Clustered data: a few prototypes with bit noise, so the tree has real structure.
    protos = torch.randint(-2**63, 2**63 - 1, (6, 4), generator=g, dtype=torch.int64)
    pick = torch.randint(0, 6, (D, K), generator=g)
    noise = torch.randint(-2**63, 2**63 - 1, (3, D, K, 4), generator=g, dtype=torch.int64)
    desc = protos[pick] ^ (noise[0] & noise[1] & noise[2])
    valid = torch.rand(D, K, generator=g) > 0.1
    voc = Vocabulary.train(desc, valid, k=k, L=L, generator=g)
    return voc, desc, valid


def test_train_structure_and_medians():
    k, L = 3, 3
    voc, desc, valid = _train_small(k=k, L=L)
    x = desc[valid]
    children = {i: [c for c in voc.children[i].tolist() if c >= 0] for i in range(voc.num_nodes)}
    assert all(len(c) <= k for c in children.values())
    # depth <= L, every leaf has a word, inner nodes (and the root) have none
    assert voc.depth <= L
    assert torch.equal(voc.node_word >= 0, voc.is_leaf)
    assert voc.num_words == int(voc.is_leaf.sum()) > k
    # Descend every training descriptor and collect the set passing through each node.
    xs = [to_int(r) for r in x.tolist()]
    descs = {i: to_int(voc.node_desc[i].tolist()) for i in range(voc.num_nodes)}
    through = {i: [] for i in range(voc.num_nodes)}
    for d in xs:
        n = 0
        through[0].append(d)
        while children[n]:
            n = min(children[n], key=lambda c: (bin(d ^ descs[c]).count("1"), children[n].index(c)))
            through[n].append(d)
    for p, ch in children.items():
        if not ch:
            continue
        grp = through[p]
        if len(grp) <= k:  # one child per descriptor, in order
            assert [descs[c] for c in ch] == grp
        else:  # converged k-medians: child = bitwise majority (ties -> 0) of its group
            assert len(ch) <= k
            for c in ch:
                members = through[c]
                maj = 0
                for i in range(256):
                    if 2 * sum((m >> i) & 1 for m in members) > len(members):
                        maj |= 1 << i
                assert descs[c] == maj
    # IDF = ln(D / N_i), N_i = documents with a descriptor transformed to word i
    D = desc.shape[0]
    words, _ = voc.transform_words(desc, valid)
    for wid in range(voc.num_words):
        ni = int(((words == wid) & valid).any(1).sum())
        want = math.log(D / ni) if ni else 0.0
        assert abs(float(voc.word_weights[wid]) - want) < 1e-12


def test_train_save_load_identical(tmp_path):
    voc, desc, valid = _train_small(seed=3)
    p = tmp_path / "v.npz"
    voc.save(p)
    voc2 = Vocabulary.load(p)
    b1, b2 = voc.transform(desc, valid), voc2.transform(desc, valid)
    assert torch.equal(b1.words, b2.words) and torch.equal(b1.weights, b2.weights)
    assert torch.equal(voc.children, voc2.children)
    assert not list(tmp_path.glob("*.tmp"))
    s = b1.weights.sum(1)
    assert torch.allclose(s, torch.ones_like(s))


def test_train_is_seeded():
    v1, desc, valid = _train_small(seed=5)
    v2, _, _ = _train_small(seed=5)
    assert torch.equal(v1.node_desc, v2.node_desc)


def test_bad_inputs():
    voc, desc, valid = _train_small(seed=1)
    with pytest.raises(ValueError):
        voc.transform(desc.to(torch.int32))
    with pytest.raises(ValueError):
        voc.transform(desc, valid[:, :3])
    with pytest.raises(ValueError):
        Vocabulary.train(desc[0], k=3, L=2)


def test_train_identical_descriptors_stops_seeding():
    # k-means++ stops when every distance is 0 (DBoW2): one child per level, a chain to depth L.
    d = torch.tensor([[1, -2, 3, -4]], dtype=torch.int64).expand(3, 10, 4).contiguous()
    voc = Vocabulary.train(d, k=3, L=3, generator=torch.Generator().manual_seed(0))
    assert voc.num_nodes == 4 and voc.num_words == 1 and voc.depth == 3
    assert torch.equal(voc.node_desc[1:], d[0, :3])
    assert float(voc.word_weights[0]) == 0.0  # in every document: ln(3/3) = 0, a stop word
    bow = voc.transform(d)
    assert (bow.words == -1).all() and (bow.weights == 0).all()
