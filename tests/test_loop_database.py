"""Place database: inverted-file L1 scores vs dense, VINS max_id / latest-entry / loop rules."""

from __future__ import annotations

import pytest
import torch

from torch_frontend.loop.database import PlaceDatabase
from torch_frontend.loop.vocabulary import BowVector, bow_to_dense

W = 60


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def rand_bows(n, seed, K=12, vocab=W):
    """Random L1-normalised sparse bags: (n, K) words ascending then -1."""
    g = torch.Generator().manual_seed(seed)
    words = torch.full((n, K), -1, dtype=torch.int64)
    weights = torch.zeros(n, K, dtype=torch.float64)
    for i in range(n):
        m = int(torch.randint(1, K + 1, (1,), generator=g))
        w = torch.randperm(vocab, generator=g)[:m].sort().values
        v = torch.rand(m, generator=g, dtype=torch.float64) + 0.05
        words[i, :m] = w
        weights[i, :m] = v / v.sum()
    return BowVector(words, weights)


def dense_l1(q, db):
    """1 - ½‖v − w‖₁ for every (query, entry) pair, dense."""
    a = bow_to_dense(q, W)
    b = bow_to_dense(db, W)
    return 1 - 0.5 * (a[:, None, :] - b[None, :, :]).abs().sum(-1)


def shares(q, db):
    a = bow_to_dense(q, W) > 0
    b = bow_to_dense(db, W) > 0
    return (a[:, None, :] & b[None, :, :]).any(-1)


def row(bow, i):
    return BowVector(bow.words[i:i + 1], bow.weights[i:i + 1])


@pytest.mark.parametrize("tail_min", [4096, 5])
def test_add_ids_and_scores_equal_dense(device, tail_min):
    entries = rand_bows(30, 0)
    db = PlaceDatabase(W, device=device)
    db.tail_min = tail_min  # 5: the tail run is merged into the main run many times
    ids = [db.add(row(entries, i)) for i in range(20)]
    ids += db.add_many(BowVector(entries.words[20:], entries.weights[20:]), streams=[0] * 10).tolist()
    assert ids == list(range(30)) and db.size() == 30
    assert db.num_postings == int((entries.words >= 0).sum())
    q = rand_bows(6, 1)
    scores, hits = db.scores_many(q)
    ref = dense_l1(q, entries)
    sh = shares(q, entries)
    assert torch.equal(hits.cpu(), sh)
    assert torch.allclose(scores.cpu()[sh], ref[sh], atol=1e-12)
    assert torch.allclose(ref[~sh], torch.zeros(1, dtype=torch.float64), atol=1e-12)
    # top-k equals the dense ranking (ties by smaller id)
    ids, sc = db.query_many(q, max_results=4)
    for b in range(q.words.shape[0]):
        cand = [(-float(ref[b, e]), e) for e in range(30) if sh[b, e]]
        want = [e for _, e in sorted(cand)[:4]]
        got = [int(e) for e in ids[b] if e >= 0]
        assert got == want
        assert torch.allclose(sc[b, :len(want)].cpu(), ref[b, want], atol=1e-12)
        assert (sc[b].cpu()[:-1] >= sc[b].cpu()[1:]).all()


def test_max_id_rule_and_latest_entry():
    same = rand_bows(1, 3)
    db = PlaceDatabase(W)
    for _ in range(20):
        db.add(same)  # every entry scores exactly 1
    ids, sc = db.query(same, max_results=10, max_id=5)
    assert ids.tolist() == [0, 1, 2, 3, 4, 19]  # entries < max_id plus the latest entry
    assert torch.allclose(sc, torch.ones_like(sc))
    ids, _ = db.query(same, max_results=30, max_id=-1)
    assert ids.tolist() == list(range(20))  # -1: no limit
    ids, _ = db.query(same, max_results=4, max_id=-7)
    assert ids.tolist() == [19]  # negative max_id: only the latest entry passes
    ids, _ = db.query(same, max_results=4, max_id=0)
    assert ids.tolist() == [19]
    # no shared word -> no result at all
    other = BowVector(torch.tensor([[W - 1 if int(same.words[0, 0]) != W - 1 else W - 2]]),
                      torch.ones(1, 1, dtype=torch.float64))
    ids, _ = db.query(other)
    assert ids.numel() == 0


def test_streams_are_isolated_and_query_many_matches_separate_databases():
    e0, e1 = rand_bows(15, 10), rand_bows(15, 11)
    multi = PlaceDatabase(W, num_streams=2)
    d0, d1 = PlaceDatabase(W), PlaceDatabase(W)
    for i in range(15):
        got = multi.add_many(BowVector(torch.cat([e0.words[i:i + 1], e1.words[i:i + 1]]),
                                       torch.cat([e0.weights[i:i + 1], e1.weights[i:i + 1]])))
        assert got.tolist() == [i, i]
        d0.add(row(e0, i))
        d1.add(row(e1, i))
    q = rand_bows(4, 12)
    streams = torch.tensor([0, 1, 1, 0])
    max_id = torch.tensor([-1, 7, 3, 10])
    ids, sc = multi.query_many(q, 4, max_id, streams)
    for b in range(4):
        ref_db = d0 if streams[b] == 0 else d1
        rid, rsc = ref_db.query(row(q, b), 4, int(max_id[b]))
        n = rid.numel()
        assert ids[b, :n].tolist() == rid.tolist() and (ids[b, n:] == -1).all()
        assert torch.allclose(sc[b, :n], rsc)


def _loop_sequence(n, seed):
    """n keyframes of mutually unrelated bags (disjoint word sets), so only planted loops score."""
    words = torch.arange(n * 4, dtype=torch.int64).reshape(n, 4) % (n * 4)
    weights = torch.full((n, 4), 0.25, dtype=torch.float64)
    return BowVector(words, weights)


def test_detect_loop_vins_rule():
    n = 60
    seq = _loop_sequence(n, 0)
    Wn = n * 4
    db = PlaceDatabase(Wn)
    for i in range(55):
        assert db.detect_loop(row(seq, i), i) == -1  # nothing similar yet
    assert db.size() == 55  # detect_loop always adds
    # keyframe 55 revisits keyframes 3 (3 shared words) and 2 (1 shared word: score 0.25 > 0.015)
    q = BowVector(torch.tensor([[8, 12, 13, 14]]), torch.full((1, 4), 0.25, dtype=torch.float64))
    ids, sc = db.query(q, 4, 55 - 50)
    assert ids.tolist() == [3, 2] and sc.tolist() == pytest.approx([0.75, 0.25])
    assert db.detect_loop(q, 55) == 2  # the OLDEST qualifying candidate, not the best
    assert db.size() == 56
    # the same decision with the scores a score plot needs: candidate 2 (0.25), best 0.75
    db2 = PlaceDatabase(Wn)
    for i in range(55):
        db2.add(row(seq, i))
    cand, cand_score, best = db2.detect_loop_many(q, [55], [0], return_scores=True)
    assert cand.tolist() == [2] and cand_score.tolist() == pytest.approx([0.25]) and best.tolist() == pytest.approx([0.75])
    cand, cand_score, best = db2.detect_loop_many(row(seq, 56), [56], [0], return_scores=True)
    assert cand.tolist() == [-1] and cand_score.tolist() == [0.0]


def test_detect_loop_thresholds_and_gate():
    n = 60
    seq = _loop_sequence(n, 0)
    # second candidate too weak: ret[1].score <= 0.015 -> no loop
    words = torch.full((1, 100), -1, dtype=torch.int64)
    weights = torch.zeros(1, 100, dtype=torch.float64)
    Wn = n * 4 + 200
    db = PlaceDatabase(Wn)
    for i in range(55):
        db.add(row(seq, i))
    # query: 0.9 on keyframe 3's words, 0.01 on a keyframe-2 word, rest on fresh words
    words[0, :4] = torch.tensor([8, 12, 13, 14])
    weights[0, :4] = torch.tensor([0.01, 0.3, 0.3, 0.3], dtype=torch.float64)
    words[0, 4:5] = n * 4 + 1
    weights[0, 4:5] = 0.09
    q = BowVector(words[:, :5], weights[:, :5])
    ids, sc = db.query(q, 4, 5)
    assert ids.tolist() == [3, 2] and float(sc[1]) == pytest.approx(0.01)
    assert db.detect_loop(q, 55) == -1
    # first candidate too weak: best <= 0.05 -> no loop
    db2 = PlaceDatabase(Wn)
    for i in range(55):
        db2.add(row(seq, i))
    q2 = BowVector(torch.tensor([[8, 12, n * 4 + 1]]), torch.tensor([[0.04, 0.04, 0.92]], dtype=torch.float64))
    assert db2.detect_loop(q2, 55) == -1
    # index gate: at index 49 max_id = -1 means "no limit" and strong candidates exist, but
    # VINS also requires index > 50
    db3 = PlaceDatabase(Wn)
    for i in range(49):
        db3.add(row(seq, i))
    qs = BowVector(torch.tensor([[8, 12, 13, 14]]), torch.full((1, 4), 0.25, dtype=torch.float64))
    ids, sc = db3.query(qs, 4, 49 - 50)
    assert ids.tolist()[:2] == [3, 2]
    assert db3.detect_loop(qs, 49) == -1
    # index 51 with the same content finds the loop (and index 50 does not)
    db4 = PlaceDatabase(Wn)
    for i in range(51):
        db4.add(row(seq, i))
    db5 = PlaceDatabase(Wn)
    for i in range(50):
        db5.add(row(seq, i))
    assert db5.detect_loop(qs, 50) == -1
    assert db4.detect_loop(qs, 51) == -1  # max_id = 1: keyframes 2, 3 are too recent
    db6 = PlaceDatabase(Wn)
    for i in range(54):
        db6.add(row(seq, i))
    assert db6.detect_loop(qs, 54) == 2  # max_id = 4


def test_detect_loop_many_matches_per_stream():
    n = 60
    seq = _loop_sequence(n, 0)
    Wn = n * 4
    multi = PlaceDatabase(Wn, num_streams=2)
    singles = [PlaceDatabase(Wn), PlaceDatabase(Wn)]
    for i in range(55):
        b = BowVector(torch.cat([seq.words[i:i + 1], seq.words[(i + 7) % n:(i + 7) % n + 1]]),
                      torch.cat([seq.weights[i:i + 1], seq.weights[i:i + 1]]))
        out = multi.detect_loop_many(b, i)
        ref = [singles[s].detect_loop(row(b, s), i) for s in range(2)]
        assert out.tolist() == ref
    q = BowVector(torch.tensor([[8, 12, 13, 14], [40, 41, 44, 45]]), torch.full((2, 4), 0.25, dtype=torch.float64))
    out = multi.detect_loop_many(q, torch.tensor([55, 55]))
    ref = [singles[s].detect_loop(row(q, s), 55) for s in range(2)]
    assert out.tolist() == ref and out[0] == 2
