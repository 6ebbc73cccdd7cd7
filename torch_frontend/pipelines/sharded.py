"""The pipelines sharded over the ranks of a ``torch.distributed`` job (``torchrun ... -m
torch_frontend track|loop|vocabulary train``): :func:`run_track_sharded`,
:func:`run_loop_sharded`, :func:`run_vocabulary_train_sharded`.

Convention:
    Every rank runs the same function with the same arguments. Inputs are sharded by input order
    in contiguous blocks (``distributed.shard_indices``); a rank's inputs are its batch. A rank
    runs on ``cuda:{LOCAL_RANK}`` when CUDA is present (``device=None``; ``"cuda"`` means the same,
    ``"cpu"`` forces the CPU), else on the CPU (gloo). Option and config errors are raised on
    every rank before any work; a rank's own failure (a bad input, a killed or stalled rank) stops
    the job as ``distributed.job`` describes, naming the rank and its inputs.

    Output layout of ``track`` (and of ``loop`` with separate graphs) in ``out``:

    * ``stream<b>/``: the complete output set of input ``b`` (0-based, input order), the files
      one process writes for that input alone (``track``: ``outputs.RunRecorder``; ``loop``:
      ``loop.report``), written atomically by the rank that owns it as soon as it is complete;
    * ``index.json``: per input its folder, rank, input and counts; ``summary.json``: the merged
      summary (the one-process summary of all inputs, plus ``distributed``: world size, backend
      and per-rank times), both written by rank 0 after every rank succeeded, then the marker
      ``written-by-torch-frontend.json`` (kind ``track-sharded`` / ``loop-sharded``). A failed
      job writes no ``summary.json``: the ``stream<b>/`` folders present are complete, the others
      absent.

    Before any rank writes, rank 0 checks ``out``: absent, empty, or holding only this layout
    (``stream<b>/`` folders the library wrote, the merged files, temporaries); anything else is
    refused (``OutputFolderError``) and nothing is touched. It then removes the previous job's
    merged files and ``stream<b>/`` folders, so ``out`` holds this job's outputs only.

    ``loop`` with a shared map (the default) needs one pose graph: every rank tracks, triangulates
    and describes its inputs' keyframes (FAST + BRIEF, the expensive part), rank 0 gathers them,
    trains the vocabulary when asked, builds the graph and writes the one-process output set of
    ``loop`` into ``out`` (plus ``distributed`` in its summary). With separate graphs a trained
    vocabulary is trained once on every input's keyframes (as one process does) and shared.

    ``vocabulary train``: every rank describes its images; k-medians runs over all ranks
    (``distributed.train_vocabulary``: the same vocabulary as one process with the same seed);
    rank 0 writes the file.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

from ..errors import ConfigError, DataError
from .common import OptionError, resolve_device

__all__ = ["INDEX", "SUMMARY", "prepare_sharded_out", "run_loop_sharded", "run_track_sharded",
           "run_vocabulary_train_sharded"]

SUMMARY = "summary.json"
INDEX = "index.json"
_STREAM_DIR = re.compile(r"stream\d+")
_TEMPORARY = re.compile(r"\.(stream\d+|summary\.json|index\.json|written-by-torch-frontend\.json)"
                        r"\.tf\d+-[A-Za-z0-9_]+\.(tmp|old)")
_SHOWN = 3


# ----------------------------------------------------------------------------------------------
# shared


def exit_code_of(exc: BaseException) -> int:
    """The CLI's exit code for a rank's failure (2: usage, option and config errors; 1: others)."""
    return 2 if isinstance(exc, (OptionError, ConfigError)) else 1


def _rank_device(device):
    """This rank's ``torch.device`` (module docstring), checked like a pipeline's ``device``."""
    from ..distributed import dist_env, rank_device

    return resolve_device(rank_device(dist_env().local_rank, device))


def _inputs_text(names: Sequence[str]) -> str:
    return ", ".join(names)


def _source_name(src) -> str:
    from .inputs import source_name

    return source_name(src)


def prepare_sharded_out(out, legacy: Sequence[str], resume: bool = False, inputs: Optional[int] = None) -> Path:
    """Check ``out`` for a sharded run and clear the previous job's outputs (module docstring);
    ``legacy``: what a ``stream<b>/`` folder may hold (the writer's ``LEGACY_OUTPUTS``). Returns
    ``out``. Raises ``OutputFolderError`` (nothing touched) for anything else in ``out``.

    ``resume`` (``--resume``, or a restart under torch elastic: ``pipelines.elastic``): the
    ``stream<b>/`` folders of the ``inputs`` inputs stay (the interrupted job's finished ones; the
    ranks replace the others as they finish them); the merged files go all the same."""
    from .._atomic import MARKER, OutputFolderError, check_replaceable, clean_stale

    out = Path(out)
    if os.path.lexists(out) and not out.is_dir():
        raise OutputFolderError(f"{out}: cannot write the outputs here: it is a file, not a folder "
                                f"(left as it is; choose another name)")
    out.mkdir(parents=True, exist_ok=True)
    foreign: List[str] = []
    streams: List[Path] = []
    temporaries: List[str] = []
    for e in sorted(os.scandir(out), key=lambda e: e.name):
        is_dir = e.is_dir(follow_symlinks=False)
        if e.name in (SUMMARY, INDEX, MARKER) and not is_dir and not e.is_symlink():
            continue
        if _STREAM_DIR.fullmatch(e.name) and is_dir:
            check_replaceable(Path(e.path), legacy)  # names the sub-folder and its foreign files
            streams.append(Path(e.path))
            continue
        m = _TEMPORARY.fullmatch(e.name)
        if m:
            temporaries.append(m.group(1))
            continue
        foreign.append(e.name + ("/" if is_dir else ""))
    if foreign:
        shown = ", ".join(foreign[:_SHOWN]) + (" and more" if len(foreign) > _SHOWN else "")
        raise OutputFolderError(f"{out}: not used for a sharded run: it holds {shown}, which a sharded run does "
                                f"not write (it writes stream<b>/, {INDEX}, {SUMMARY}); move them away or "
                                f"choose another folder")
    for name in (SUMMARY, INDEX, MARKER):  # the summary first: it is what says "complete"
        (out / name).unlink(missing_ok=True)
    for p in streams:
        if resume and inputs is not None and int(p.name[len("stream"):]) < inputs:
            continue
        shutil.rmtree(p)
    for name in sorted(set(temporaries)):
        clean_stale(out / name)  # a killed job's; a live process's stay
    return out


def _write_merged(out: Path, kind: str, summary: Dict[str, Any], index: Dict[str, Any]) -> None:
    """``index.json``, then ``summary.json``, then the marker (each atomic)."""
    from .._atomic import MARKER, _manifest, write_text_atomic

    write_text_atomic(out / INDEX, json.dumps(index, indent=2) + "\n")
    write_text_atomic(out / SUMMARY, json.dumps(summary, indent=2) + "\n")
    write_text_atomic(out / MARKER, _manifest(out, kind))


def _backend() -> str:
    import torch.distributed as dist

    return str(dist.get_backend()) if dist.is_initialized() else "none (one process)"


def _prepare(job, out: Path, legacy: Sequence[str], resume: bool = False, inputs: Optional[int] = None) -> None:
    """Rank 0 prepares ``out`` while the others wait (a refusal fails the job on every rank)."""
    job.run(lambda: prepare_sharded_out(out, legacy, resume, inputs) if job.rank == 0 else None, exit_code_of,
            phase="prepare")


def _rank_stage(out: Path, job, opt, world_inputs: int, holder: List[Any]):
    """The factory ``track_streams`` / the loop's ranks call with their fingerprint: this rank's
    ``elastic.RankStage`` (the job's fingerprint: the rank's, the world size and the rank), kept in
    ``holder`` for the end of the job."""
    from .elastic import RankStage, resuming

    def make(fp: Dict[str, str]):
        fp = {**fp, "world size": str(job.world_size), "rank": str(job.rank), "job inputs": str(world_inputs)}
        holder.append(RankStage(out, job.rank, fp, opt.checkpoint_every, resuming(opt.resume)))
        return holder[-1]
    return make


def _work_with_stage(work, holder: List[Any]):
    """``work`` whose rank stage (made inside it) is kept or removed as ``RankStage.stop`` says when
    it raises."""
    def run():
        try:
            return work()
        except BaseException as exc:
            for st in holder:
                st.stop(exc)
            raise
    return run


def _finish_job(job, holder: List[Any], merge) -> Any:
    """Rank 0's ``merge()`` (the merged files) as the job's last phase, then every rank removes
    its staging folder (the job is complete). Returns what ``merge`` returned on rank 0."""
    box: Dict[str, Any] = {}

    def phase():
        if job.rank == 0:
            box["result"] = merge()
    job.run(phase, exit_code_of, phase="merge")
    # meet once more: rank 0 may host the store (no launcher agent), and a rank still reading the
    # merge phase's outcomes must not find it gone
    job.barrier()
    for st in holder:
        st.close()
    return box.get("result")


# ----------------------------------------------------------------------------------------------
# track


def run_track_sharded(config, sources: Sequence[Any], out, options=None, *, timeout: Optional[float] = None
                      ) -> Optional[Dict[str, Any]]:
    """``run_track`` over the ranks of this job (module docstring): returns the merged summary on
    rank 0, None on the others.

    Raises (besides ``run_track``'s, raised on every rank before any work):
        distributed.RankFailure (rank 0), the rank's own error with its rank and inputs (a failed
        rank), distributed.JobAborted (the other ranks), distributed.JobInterrupted.
    """
    from ..distributed import Job, shard_indices
    from ..distributed.env import DEFAULT_TIMEOUT
    from ..outputs import LEGACY_OUTPUTS
    from .inputs import resolve_configs
    from .track import TrackOptions, track_streams

    t_start = time.perf_counter()
    opt = TrackOptions() if options is None else options
    sources = list(sources)
    if not sources:
        raise OptionError("sources", "sources: no input given (expected at least one (kind, path) or io Sequence)")
    dev = _rank_device(opt.device)
    opt = dataclasses.replace(opt, device=str(dev))
    opt.check()
    cfgs = resolve_configs(config, sources, opt.camera)  # every input's, on every rank: errors before any work
    out = Path(out)
    from ..distributed import dist_env

    env = dist_env()
    mine = list(shard_indices(len(sources), env.rank, env.world_size))
    from .elastic import resuming

    with Job("track", _inputs_text([_source_name(sources[i]) for i in mine]),
             DEFAULT_TIMEOUT if timeout is None else timeout, device=dev) as job:
        _prepare(job, out, LEGACY_OUTPUTS, resuming(opt.resume), len(sources))
        if env.rank != 0:
            opt = dataclasses.replace(opt, progress=False)
        extra = {"distributed": {"rank": env.rank, "world_size": env.world_size, "batch": mine}}
        holder: List[Any] = []

        def work():
            _same_lk_backend(job, opt.lk_backend, dev)
            if not mine:
                return None
            return track_streams([cfgs[i] for i in mine], [sources[i] for i in mine], [out / f"stream{i}" for i in mine],
                                 opt, extra=extra, beat=job.beat, stage=_rank_stage(out, job, opt, len(sources), holder))

        res = job.run(_work_with_stage(work, holder), exit_code_of)
        gathered = job.gather({"rank": env.rank, "streams": mine, "result": res, "host": os.uname().nodename})

        def merge():
            summary, index = _merge_track(gathered, sources, cfgs, opt, out, job, time.perf_counter() - t_start)
            _write_merged(out, "track-sharded", summary, index)
            return summary
        return _finish_job(job, holder, merge)


def _same_lk_backend(job, requested, dev) -> None:
    """Every rank resolves the tracker's kernels alike (``fused.resolve_backend``), or every rank raises
    ``OptionError`` before any work: a rank without numba would fall back to the tensor LK and give
    other bits than the others (and than one process)."""
    from ..fused import resolve_backend

    mine = resolve_backend(requested, dev)
    every = job.all_gather(mine)
    if len(set(every)) > 1:
        ranks = ", ".join(f"rank {r}: {b}" for r, b in enumerate(every))
        raise OptionError("lk_backend", f"lk_backend: the ranks resolve different LK kernels ({ranks}); install numba "
                                        f"on every node or give every rank lk_backend tensor (or fused)")


def _merge_track(gathered, sources, cfgs, opt, out: Path, job, seconds: float) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """The merged ``summary.json`` (the one-process summary of all inputs) and ``index.json``."""
    import numpy as np

    from ..outputs import run_counts
    from .inputs import config_label

    per: List[Dict[str, Any]] = []  # per input, in input order (ranks hold contiguous blocks)
    owner: List[int] = []
    ranks = []
    for g in gathered:
        res = g["result"]
        ranks.append({"rank": g["rank"], "host": g["host"], "streams": g["streams"],
                      **({k: res[k] for k in ("device", "steps", "seconds", "tracker_seconds", "decode_seconds",
                                              "input_wait_seconds")} if res else {})})
        if res:
            per += res["streams"]
            owner += [g["rank"]] * len(res["streams"])
    sums = [p["summary"] for p in per]
    lengths = np.concatenate([p["lengths"] for p in per]) if per else np.zeros(0, dtype=np.int64)
    frames = sum(s["frames"] for s in sums)
    published = sum(s["published"] for s in sums)
    n_feat = sum(s["published_features"] for s in sums)
    skipped = [{**k, "stream": b} for b, s in enumerate(sums) for k in s["skipped"]]
    summary = {
        **run_counts(len(sums), frames, published, n_feat, lengths, seconds, skipped,
                     sum(s["track_images"] for s in sums)),
        "per_stream": [s["per_stream"][0] for s in sums],
        "steps": max((s["steps"] for s in sums), default=0),
        "tracker_seconds": round(sum(r.get("tracker_seconds", 0.0) for r in ranks), 6),
        "workers": int(opt.workers),
        "decode_seconds": round(sum(r.get("decode_seconds", 0.0) for r in ranks), 6),
        "input_wait_seconds": round(sum(r.get("input_wait_seconds", 0.0) for r in ranks), 6),
        "config": config_label(cfgs),
        "mode": opt.mode,
        "device": ranks[0].get("device", opt.device) if ranks else opt.device,
        "lk_backend": sums[0]["lk_backend"] if sums else None,  # every rank's (checked before any work)
        "inputs": [s["inputs"][0] for s in sums],
        "out": str(out),
        "distributed": {"world_size": job.world_size, "backend": _backend(),
                        "sharding": "contiguous blocks in input order", "ranks": ranks},
        "index": INDEX,
    }
    index = {
        "kind": "track",
        "world_size": job.world_size,
        "streams": [{"stream": b, "name": s["per_stream"][0]["name"], "folder": f"stream{b}", "rank": owner[b],
                     "input": s["inputs"][0], "frames": s["frames"], "published": s["published"],
                     "published_features": s["published_features"], "tracks": s["tracks"],
                     "skipped_bad_frames": s["skipped_bad_frames"]} for b, s in enumerate(sums)],
    }
    return summary, index


# ----------------------------------------------------------------------------------------------
# vocabulary train


def run_vocabulary_train_sharded(images: Sequence[Any], out, options=None, *, timeout: Optional[float] = None
                                 ) -> Optional[Dict[str, Any]]:
    """``run_vocabulary_train`` over the ranks of this job: every rank describes its block of the
    images, k-medians runs over all ranks, rank 0 writes ``out`` and returns the summary (None on
    the others). The vocabulary is the one one process trains with the same options."""
    import torch

    from ..distributed import Job, dist_env, shard_indices, train_vocabulary
    from ..distributed.env import DEFAULT_TIMEOUT
    from .common import pad_ragged, progress_bar
    from .vocabulary import VocabularyOptions, _check_out, _describe_images, vocabulary_images

    t0 = time.perf_counter()
    opt = VocabularyOptions() if options is None else options
    dev = _rank_device(opt.device)
    opt = dataclasses.replace(opt, device=str(dev))
    opt.check()
    out = Path(out)
    _check_out(out)
    files = vocabulary_images(images, opt.max_images)
    env = dist_env()
    mine = list(shard_indices(len(files), env.rank, env.world_size))
    what = f"images {mine[0] + 1}-{mine[-1] + 1} of {len(files)}: {files[mine[0]]} .. {files[mine[-1]]}" if mine else ""
    with Job("vocabulary", what, DEFAULT_TIMEOUT if timeout is None else timeout, device=dev) as job:
        progress = opt.progress if env.rank == 0 else False
        state: Dict[str, Any] = {}

        def work():
            with progress_bar(progress, len(mine), "describing", "image") as bar:
                descs = _describe_images([files[i] for i in mine], opt, dev, bar, beat=job.beat)
                state["verbose"] = bar is not None and not bar.disable
            return descs

        descs = job.run(work, exit_code_of)
        n_desc = sum(job.all_gather(sum(int(d.shape[0]) for d in descs)))
        if n_desc == 0:
            raise DataError(f"no FAST corners (threshold {opt.fast_threshold}) in any of the {len(files)} images")
        if descs:
            desc, valid = pad_ragged(descs, device=dev)
        else:
            desc = torch.zeros(0, 1, 4, dtype=torch.int64, device=dev)
            valid = torch.zeros(0, 1, dtype=torch.bool, device=dev)
        t_desc = time.perf_counter() - t0
        gen = torch.Generator(device=dev).manual_seed(int(opt.seed))
        voc = train_vocabulary(desc, valid, k=opt.k, L=opt.L, generator=gen,
                               progress=bool(state.get("verbose")) and env.rank == 0)
        if env.rank != 0:
            return None
        if out.suffix.lower() == ".bin":
            voc.save_vins_bin(out)
        else:
            voc.save(out)
        seconds = time.perf_counter() - t0
        return {"images": len(files), "descriptors": n_desc, "words": int(voc.num_words),
                "nodes": int(voc.num_nodes), "k": opt.k, "L": opt.L, "seconds": round(seconds, 3),
                "describe_seconds": round(t_desc, 3), "out": str(out), "device": str(dev),
                "distributed": {"world_size": env.world_size, "backend": _backend()}}


# ----------------------------------------------------------------------------------------------
# loop


def run_loop_sharded(config, sources: Sequence[Any], poses: Sequence[Any], out=None, options=None, *,
                     ground_truth: Optional[Sequence[Any]] = None, timeout: Optional[float] = None
                     ) -> Optional[Dict[str, Any]]:
    """``run_loop`` over the ranks of this job (module docstring): a shared map is built on rank 0
    from every rank's keyframes (the one-process outputs in ``out``), separate graphs per input on
    the input's rank (``out/stream<b>/``, merged ``summary.json`` and ``index.json``). Returns the
    (merged) summary on rank 0, None on the others; ``out=None`` writes nothing."""
    from ..distributed import Job, dist_env, shard_indices
    from ..distributed.env import DEFAULT_TIMEOUT
    from .elastic import resuming
    from .inputs import resolve_configs
    from .loop import (
        LoopOptions,
        _check_arguments,
        _open_inputs,
        _prepare_streams,
        save_prepared,
        stream_extrinsics,
    )
    from .loop_checkpoint import LoopCheckpoints, loop_fingerprint

    t_start = time.perf_counter()
    opt = LoopOptions() if options is None else options
    sources, poses = list(sources), list(poses)
    gts = [None] * len(sources) if ground_truth is None else list(ground_truth)
    dev = _rank_device(opt.device)
    opt = dataclasses.replace(opt, device=str(dev))
    _check_arguments(sources, poses, gts, opt)
    # every input's config (and the shared map's one extrinsic), on every rank: errors before any work
    cfgs = resolve_configs(config, sources, opt.camera)
    stream_extrinsics(cfgs, opt)
    if out is not None and not opt.separate_graphs:
        from ..loop.report import check_out_folder

        check_out_folder(out)
    env = dist_env()
    mine = list(shard_indices(len(sources), env.rank, env.world_size))
    ropt = opt if env.rank == 0 else dataclasses.replace(opt, progress=False)
    with Job("loop", _inputs_text([_source_name(sources[i]) for i in mine]),
             DEFAULT_TIMEOUT if timeout is None else timeout, device=dev) as job:

        def prepare():
            if job.rank != 0:
                return None
            t0 = time.perf_counter()
            if out is not None and opt.separate_graphs:
                from ..loop.report import LEGACY_OUTPUTS

                prepare_sharded_out(out, LEGACY_OUTPUTS, resuming(opt.resume), len(sources))
            voc = None
            if opt.vocabulary is not None and not opt.separate_graphs:  # the graph's rank loads it
                from ..loop.vocabulary import Vocabulary
                from .vocabulary import load_vocabulary

                voc = opt.vocabulary if isinstance(opt.vocabulary, Vocabulary) else load_vocabulary(opt.vocabulary)
            return voc, time.perf_counter() - t0

        prepared = job.run(prepare, exit_code_of, phase="prepare")
        holder: List[Any] = []

        def work():
            if not mine:
                return None
            times: Dict[str, float] = {}
            my_poses, my_gts = [poses[i] for i in mine], [gts[i] for i in mine]
            inp = _open_inputs([cfgs[i] for i in mine], [sources[i] for i in mine], my_poses, my_gts, ropt, times,
                               load_vocabulary=opt.separate_graphs)
            ck = None
            if out is not None:  # the rank's checkpoints in its staging folder beside out
                fp = loop_fingerprint(inp.cfgs, [sources[i] for i in mine], inp.seqs, my_poses, my_gts, ropt, dev)
                ck = LoopCheckpoints.of_rank(_rank_stage(Path(out), job, opt, len(sources), holder)(fp))
            prep = _prepare_streams(inp, ropt, times, beat=job.beat, ck=ck)
            if ck is not None and not ck.past_tracking:
                save_prepared(ck, prep, times, {})
            return inp, prep, times, ck

        res = job.run(_work_with_stage(work, holder), exit_code_of)
        if opt.separate_graphs:
            summary = _separate_graphs(job, res, mine, opt, ropt, out, t_start, holder)
        else:
            summary = _shared_map(job, res, mine, prepared, gts, opt, out, t_start)
        for st in holder:  # the job is complete
            st.close()
        return summary


def _shareable(inp, prep, keep_images: bool):
    """What rank 0 needs of a rank's inputs and stages 1-4 (no readers, no observations, images
    only when kept)."""
    inp = dataclasses.replace(inp, seqs=[], vocabulary=None)
    for log in prep.logs:
        log.obs = []
        if not keep_images:
            log.kf_images = []
    return inp, prep


def _dist_entry(job, ranks: List[Dict[str, Any]]) -> Dict[str, Any]:
    return {"world_size": job.world_size, "backend": _backend(), "sharding": "contiguous blocks in input order",
            "ranks": ranks}


def _shared_map(job, res, mine, prepared, gts, opt, out, t_start) -> Optional[Dict[str, Any]]:
    """Rank 0 builds the one graph from every rank's keyframes and writes ``run_loop``'s outputs
    (the job's last phase: the ranks keep their checkpoints until it is done)."""
    from .loop import _finish, _Inputs, _Prepared

    payload = None
    if res is not None:
        inp, prep, times, _ = res
        payload = (*_shareable(inp, prep, opt.keep_images), times)
    gathered = job.gather({"rank": job.rank, "streams": mine, "host": os.uname().nodename, "part": payload})

    def merge():  # the ranks wait (their checkpoints kept) until the graph and outputs are written
        parts = [g["part"] for g in gathered if g["part"] is not None]
        inp_all = _Inputs([c for p in parts for c in p[0].cfgs], resolve_device(opt.device),
                          [r for p in parts for r in p[0].R_ics], [t for p in parts for t in p[0].t_ics], [],
                          [n for p in parts for n in p[0].names],
                          [t for p in parts for t in p[0].trajs], [n for p in parts for n in p[0].pose_names], list(gts),
                          [t for p in parts for t in p[0].gt_trajs], prepared[0])
        preps = [p[1] for p in parts]
        prep_all = _Prepared([x for p in preps for x in p.logs], sum(p.skipped for p in preps),
                             [x for p in preps for x in p.tri], [x for p in preps for x in p.descs],
                             {"workers": int(opt.workers),
                              "decode_seconds": round(sum(p.input_times["decode_seconds"] for p in preps), 6),
                              "input_wait_seconds": round(sum(p.input_times["input_wait_seconds"] for p in preps), 6)},
                             [x for p in preps for x in p.skipped_per_stream])
        # the stages that ran on every rank took as long as the slowest rank
        times: Dict[str, float] = {"vocabulary_load": prepared[1]}
        for key in ("tracking", "triangulation", "description"):
            times[key] = max(p[2].get(key, 0.0) for p in parts)
        ranks = [{"rank": g["rank"], "host": g["host"], "streams": g["streams"],
                  "times": {k: round(v, 6) for k, v in (g["part"][2] if g["part"] else {}).items()}} for g in gathered]
        run = _finish(inp_all, prep_all, opt, times, t_start, out, {"distributed": _dist_entry(job, ranks)})
        return run.summary
    return _finish_job(job, [], merge)


def _separate_graphs(job, res, mine, opt, ropt, out, t_start, holder=()) -> Optional[Dict[str, Any]]:
    """One graph per input on its rank (``out/stream<b>/``); rank 0 merges the summaries. With
    checkpoints (``res``'s ``LoopCheckpoints``), one as each input is written: a resumed rank
    takes the finished inputs' entries from it and writes only the others."""
    from .loop import _finish, _Inputs, _Prepared, _vocabulary
    from .loop_stages import keyframe_ate

    shared_voc = None
    if opt.train_vocabulary:  # one vocabulary from every input's keyframes, as one process trains it
        gathered = job.gather(None if res is None else res[1].descs)
        trained: Dict[str, Any] = {}

        def train():
            if job.rank == 0:
                tt: Dict[str, float] = {}
                voc, info = _vocabulary(None, [d for part in gathered if part for d in part], opt, tt)
                trained["voc"] = (voc, info, tt["vocabulary"])
        job.run(train, exit_code_of, phase="vocabulary")
        shared_voc = job.broadcast(trained.get("voc"))

    def graphs():
        if res is None:
            return []
        inp, prep, times, ck = res
        finished = dict(ck.payload.get("finished") or {}) if ck is not None else {}
        done = []
        for j, g in enumerate(mine):
            if g in finished:  # written before the checkpoint this rank continues from
                done.append(finished[g])
                continue
            inp_b = _Inputs([inp.cfgs[j]], inp.device, [inp.R_ics[j]], [inp.t_ics[j]], [inp.seqs[j]], [inp.names[j]],
                            [inp.trajs[j]],
                            [inp.pose_names[j]], [inp.gts[j]], [inp.gt_trajs[j]], inp.vocabulary)
            sk = prep.skipped_per_stream[j]
            prep_b = _Prepared([prep.logs[j]], sk, [prep.tri[j]], [prep.descs[j]], prep.input_times, [sk])
            extra = {"distributed": {"rank": job.rank, "world_size": job.world_size, "batch": mine}}
            run = _finish(inp_b, prep_b, ropt, dict(times), t_start, None if out is None else Path(out) / f"stream{g}",
                          extra, vocabulary=shared_voc)
            s = run.streams[0]
            raw = None
            if s.ground_truth is not None:  # the pooled ATE's sums, as one process adds them
                eb, n, sb, _ = keyframe_ate(s.vio, s.ground_truth, opt.max_pose_gap)
                _, _, sa, _ = keyframe_ate(s.corrected, s.ground_truth, opt.max_pose_gap)
                raw = (sb, sa, n)
            done.append({"stream": g, "summary": run.summary, "ate_sums": raw})
            if ck is not None and ck.writer.enabled:  # finished: a resumed rank does not redo it
                finished[g] = done[-1]
                ck.save(int(ck.writer.frames) + 1, "streams", {"finished": dict(finished)}, {})
                ck.kill_point("written", len(finished))  # the test hook: after the input's checkpoint
            job.beat()
        return done

    done = job.run(_work_with_stage(graphs, list(holder)), exit_code_of, phase="graphs")
    gathered = job.gather({"rank": job.rank, "streams": mine, "host": os.uname().nodename, "done": done,
                           "times": res[2] if res else {}, "input": res[1].input_times if res else {}})

    def merge():
        per = [d for g in gathered for d in g["done"]]
        ranks = [{"rank": g["rank"], "host": g["host"], "streams": g["streams"],
                  "times": {k: round(v, 6) for k, v in g["times"].items()}} for g in gathered]
        inputs = [g["input"] for g in gathered if g["input"]]
        summary, index = _merge_loop(per, opt, out, job, ranks, inputs, time.perf_counter() - t_start)
        if out is not None:
            _write_merged(Path(out), "loop-sharded", summary, index)
        return summary
    return _finish_job(job, [], merge)


def _merge_loop(per, opt, out, job, ranks, inputs, seconds: float) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """The merged summary of separate graphs (``run_loop``'s keys for all inputs) and the index."""
    import math

    sums = [p["summary"] for p in per]
    reasons: Dict[str, int] = {}
    for s in sums:
        for k, v in s["rejected_by_reason"].items():
            reasons[k] = reasons.get(k, 0) + v
    ate: Dict[str, float] = {}
    raw = [p["ate_sums"] for p in per if p["ate_sums"] is not None]
    if raw:
        sq_b = sq_a = 0.0
        n = 0
        for sb, sa, k in raw:  # in input order, as one process adds them
            sq_b, sq_a, n = sq_b + sb, sq_a + sa, n + k
        if n:
            ate = {"ate_before": math.sqrt(sq_b / n), "ate_after": math.sqrt(sq_a / n)}
    times: Dict[str, float] = {}
    for s in sums:
        for k, v in s["times"].items():
            times[k] = max(times.get(k, 0.0), v)
    keyframes = sum(s["keyframes"] for s in sums)
    first = sums[0]
    per_stream = []
    for b, s in enumerate(sums):
        e = dict(s["per_stream"][0])
        e["graph"] = b  # graph b of the job (each folder's own graph is its graph 0)
        per_stream.append(e)
    summary: Dict[str, Any] = {
        "keyframes": keyframes,
        "keyframes_loaded": sum(s["keyframes_loaded"] for s in sums),
        "keyframes_not_querying": sum(s["keyframes_not_querying"] for s in sums),
        "loop_candidates": sum(s["loop_candidates"] for s in sums),
        "loops_accepted": sum(s["loops_accepted"] for s in sums),
        "loops_rejected": sum(s["loops_rejected"] for s in sums),
        "rejected_by_reason": dict(sorted(reasons.items())),
        **ate,
        "optimisations": sum(s["optimisations"] for s in sums),
        "skipped_bad_frames": sum(s["skipped_bad_frames"] for s in sums),
        "seconds": round(float(seconds), 6),
        "times": {k: round(v, 6) for k, v in times.items()},
        "keyframes_per_second": keyframes / seconds if seconds > 0 else 0.0,
        "streams": len(sums),
        "graphs": len(sums),
        "shared_map": False,
        **{k: first[k] for k in ("mode", "up", "tracker_mode", "device", "config", "extrinsic", "keyframe_rule",
                                 "vocabulary", "load_graph")},
        "config": "; ".join(dict.fromkeys(p for s in sums for p in s["config"].split("; "))),
        "per_stream": per_stream,
        "workers": int(opt.workers),
        "decode_seconds": round(sum(i["decode_seconds"] for i in inputs), 6),
        "input_wait_seconds": round(sum(i["input_wait_seconds"] for i in inputs), 6),
        "distributed": _dist_entry(job, ranks),
        "index": INDEX,
    }
    if out is not None:
        summary["out"] = str(Path(out))
    index = {
        "kind": "loop",
        "world_size": job.world_size,
        "streams": [{"stream": p["stream"], "name": s["per_stream"][0]["name"], "folder": f"stream{p['stream']}",
                     "rank": next(r["rank"] for r in ranks if p["stream"] in r["streams"]),
                     "keyframes": s["keyframes"], "loops_accepted": s["loops_accepted"],
                     "ate_before": s.get("ate_before"), "ate_after": s.get("ate_after")}
                    for p, s in zip(per, sums)],
    }
    return summary, index
