"""The pipeline on a Ray cluster: ``python -m flowmimic.cluster pipeline --address ADDRESS -o DIR``.

Each stage of ``flowmimic pipeline`` runs as a Ray task, and each task runs the binary's own
stage (``flowmimic pipeline --only STAGE``): a cluster runs the very code one machine runs, with
the same stamps. A stage already done for the same settings and inputs is skipped; one whose
worker was killed is retried by Ray and resumes from its checkpoint. The per-clip stages (an
expert, then its noisy rollouts) run side by side, each asking Ray for ``--cpus-per-task`` CPUs
(and using as many threads); the dataset is joined from the clips' rollouts, bit for bit the
dataset one machine collects, then both models train side by side and the evaluation runs.

``DIR`` must be a directory every node sees at the same path (NFS or any shared file system), and
every node needs the ``flowmimic`` binary (``--binary``, ``$FLOWMIMIC_BIN`` or the ``PATH``).
``--address local`` starts a Ray cluster on this machine with ``--workers`` CPUs.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time
from typing import Optional, Sequence


def find_binary(explicit: Optional[str] = None) -> str:
    """The ``flowmimic`` binary, as an absolute path (tasks run in Ray's working directories):
    ``explicit``, else ``$FLOWMIMIC_BIN``, else the ``PATH``."""
    for candidate in (explicit, os.environ.get("FLOWMIMIC_BIN"), shutil.which("flowmimic")):
        if candidate:
            if not (os.path.isfile(candidate) and os.access(candidate, os.X_OK)):
                raise SystemExit(f"flowmimic.cluster: {candidate} is not an executable flowmimic binary")
            return os.path.abspath(candidate)
    raise SystemExit(
        "flowmimic.cluster: no flowmimic binary: build it (cargo build --release) and pass --binary "
        "target/release/flowmimic, set FLOWMIMIC_BIN, or put it on the PATH of every node"
    )


def _stage(binary: str, settings: Sequence[str], out: str, stage: str, cpus: int, clips: Sequence[str], *after) -> float:
    """Runs one stage of the binary's pipeline with ``cpus`` threads, once the stages ``after``
    are done (Ray waits for them); its output goes to ``out/logs/<stage>.log``. Returns the seconds
    it took; raises with the log's end when it fails."""
    logs = pathlib.Path(out) / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    log = logs / (stage.replace(":", "-") + ".log")
    command = [binary, *settings, "pipeline", "-o", out, "--only", stage]
    if stage == "clips" and clips:
        command += ["--clip", *clips]
    env = dict(os.environ, RAYON_NUM_THREADS=str(cpus))
    started = time.time()
    # Each run's output after the earlier runs', so that a rerun that skips keeps the log of
    # the run that did the work.
    with open(log, "a") as f:
        f.write(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')}: {' '.join(command)}\n")
        f.flush()
        begin = f.tell()
        done = subprocess.run(command, stdout=f, stderr=subprocess.STDOUT, env=env)
    with open(log, errors="replace") as f:
        f.seek(begin)
        output = f.read()
    if done.returncode != 0:
        tail = "".join(output.splitlines(keepends=True)[-20:])
        raise RuntimeError(f"stage {stage} failed (exit {done.returncode}); the end of {log}:\n{tail}")
    return -1.0 if "(skipped)" in output else time.time() - started


def _plan(binary: str, settings: Sequence[str], out: str) -> dict:
    """The stages after the clips, as the binary plans them for these settings (``flowmimic
    pipeline --plan``): ``experts``, ``rollouts`` (each clip with its expert) and ``models``."""
    done = subprocess.run([binary, *settings, "pipeline", "-o", out, "--plan"], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"flowmimic pipeline --plan failed: {done.stderr.strip()}")
    return json.loads(done.stdout)


def pipeline(
    address: str,
    out: str,
    binary: str,
    settings: Sequence[str] = (),
    clips: Sequence[str] = (),
    cpus_per_task: int = 1,
    train_cpus: int = 1,
    workers: Optional[int] = None,
    retries: int = 2,
) -> dict:
    """Runs the pipeline's stages as Ray tasks and returns each stage's seconds, by stage (-1 for
    a stage skipped: done before for the same settings and inputs)."""
    import ray

    if address == "local":
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    else:
        ray.init(address=address, log_to_driver=False)
    out = os.path.abspath(out)
    # Ray retries a task whose worker died (max_retries); the binary resumes the stage.
    stage = ray.remote(max_retries=retries)(_stage)
    seconds = {}

    def run(name: str, cpus: int, *after):
        return stage.options(num_cpus=cpus, name=name).remote(binary, list(settings), out, name, cpus, list(clips), *after)

    def wait(refs: dict) -> None:
        pending = dict(refs)
        while pending:
            ready, _ = ray.wait(list(pending.values()), num_returns=1)
            name = next(n for n, r in pending.items() if r == ready[0])
            seconds[name] = ray.get(pending.pop(name))
            count = f"({len(refs) - len(pending)}/{len(refs)})"
            if seconds[name] < 0:
                print(f"skipped {name}: done before for the same settings {count}", flush=True)
            else:
                print(f"done {name} in {seconds[name]:.1f} s {count}", flush=True)

    try:
        cluster = ray.cluster_resources()
        print(f"ray: {cluster.get('CPU', 0):.0f} CPUs, {cluster.get('GPU', 0):.0f} GPUs; stages in {out}", flush=True)
        started = time.time()
        wait({"clips": run("clips", 1)})
        plan = _plan(binary, settings, out)
        # Each clip's rollouts start as soon as its expert is done (one expert per clip, or one
        # policy over them all: `[pipeline] experts`).
        experts = {e: run(f"expert:{e}", cpus_per_task) for e in plan["experts"]}
        rollouts = {c: run(f"rollouts:{c}", cpus_per_task, experts[e]) for c, e in plan["rollouts"]}
        wait({**{f"expert:{e}": r for e, r in experts.items()}, **{f"rollouts:{c}": r for c, r in rollouts.items()}})
        wait({"collect": run("collect", 1)})
        # The trainer runs on CPUs only (the binary has no GPU backend): it asks for CPUs.
        wait({f"train:{o}": run(f"train:{o}", train_cpus) for o in plan["models"]})
        wait({"evaluate": run("evaluate", train_cpus)})
        print(f"pipeline finished on ray in {time.time() - started:.1f} s: report {out}/eval/report.md", flush=True)
    finally:
        ray.shutdown()
    return seconds


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m flowmimic.cluster", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser(
        "pipeline",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="flowmimic pipeline's stages as Ray tasks",
        description="Every stage of `flowmimic pipeline` as a Ray task: the experts and rollouts of the "
        "clips side by side, then the dataset, both models and the evaluation. Stages done for the same "
        "settings are skipped; interrupted ones resume.",
    )
    p.add_argument("--address", required=True, help="the Ray cluster (host:6379 or ray://host:10001), or 'local'")
    p.add_argument("-o", "--out", default="runs/pipeline", help="output directory, seen by every node")
    p.add_argument("--preset", help="the binary's preset: tiny (seconds), cpu (its default: hours) or paper")
    p.add_argument("--config", action="append", default=[], help="a TOML layer for the binary (repeatable)")
    p.add_argument("--clip", nargs="+", default=[], help="clips to train on (default: the straight walk)")
    p.add_argument("--binary", help="the flowmimic binary (none: $FLOWMIMIC_BIN, else the PATH)")
    p.add_argument("--cpus-per-task", type=int, default=1, help="CPUs (and threads) of each expert and rollouts task")
    p.add_argument("--train-cpus", type=int, default=1, help="CPUs of each model's training task")
    p.add_argument("--workers", type=int, help="with --address local: the local cluster's CPUs (none: all)")
    p.add_argument("--retries", type=int, default=2, help="times Ray retries a task whose worker died")
    args = parser.parse_args(argv)
    binary = find_binary(args.binary)
    # Absolute paths: the tasks run in Ray's working directories.
    configs = [x for c in args.config for x in ("--config", os.path.abspath(c))]
    settings = (["--preset", args.preset] if args.preset else []) + configs
    try:
        pipeline(
            args.address,
            args.out,
            binary,
            settings,
            [os.path.abspath(c) for c in args.clip],
            args.cpus_per_task,
            args.train_cpus,
            args.workers,
            args.retries,
        )
    except RuntimeError as e:
        # Ray wraps a task's exception with its traceback; the stage's own message says it all.
        sys.exit(f"flowmimic.cluster: {getattr(e, 'cause', None) or e}")


if __name__ == "__main__":
    main()
