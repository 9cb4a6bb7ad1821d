"""Bad input to every `n3dmap` subcommand ends in exit status 2 and ONE last stderr line
`n3dmap <command>: error: ...` naming what is wrong — never a traceback, never a hang.

Table-driven: each case is the argv (with {placeholders} for the fixtures below) and the text the
error line must contain. Most cases fail in argparse or before any model runs (0.1 s for argparse,
2-4 s where torch is imported); the two that reach out to a Ray job server or a zenoh router that is
not there are marked slow. The taken-port cases hold a listening socket; no server starts.
"""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration


def _case(case_id: str, argv: str, names: str, *, slow: bool = False):
    marks = [pytest.mark.slow] if slow else []
    return pytest.param(argv, names, id=case_id, marks=marks)


# (id, argv with placeholders, text the one error line must contain)
CASES = [
    # serve: ranges in argparse; taken ports before the bundle loads (was: uvicorn log + exit 3,
    # a gRPC bind traceback; --threads 0 / --max-body-mb 0 started a server)
    _case("serve-http-port-range", "serve --bundle {bundle} --http-port 70000", "--http-port"),
    _case("serve-threads-0", "serve --bundle {bundle} --threads 0", "--threads"),
    _case("serve-max-body-0", "serve --bundle {bundle} --max-body-mb 0", "--max-body-mb"),
    _case("serve-http-port-taken", "serve --bundle {bundle} --http-port {taken} --grpc-port 0", "--http-port {taken}"),
    _case("serve-grpc-port-taken", "serve --bundle {bundle} --http-port 0 --grpc-port {taken}", "--grpc-port {taken}"),
    # data: `info` without --verify printed a summary, exit 0, for a dataset missing its shard;
    # `preview --out DIR` wrote DIR.png and said it wrote DIR; a file in --out's path was a traceback
    _case("info-missing-shard", "data info {noshard}", "missing shard"),
    _case("preview-out-is-dir", "data preview {data} --out {empty}", "--out {empty} is a directory"),
    _case("preview-out-under-file", "data preview {data} --out {file}/p.png", "--out {file}/p.png: its folder {file} is a file"),
    # an output folder under a regular file: refused naming the option before the work (was: a bare
    # "[Errno 20] Not a directory" after the evaluation, or "File exists" naming the file for preview)
    _case("eval-out-under-file", "eval occupancy --data {data} --bundle {bundle} --out {file}/r",
          "--out {file}/r cannot be created: {file} is a file"),
    _case("generate-out-under-file", "data generate --out {file}/d --preset tiny --episodes 1",
          "--out {file}/d cannot be created: {file} is a file"),
    _case("train-run-dir-under-file", "train occupancy --data {data} --run-dir {file}/run --steps 1 --workers 0",
          "--run-dir {file}/run cannot be created"),
    _case("merge-out-under-file", "bundle merge {bundle} {truncated_bundle} --out {file}/m", "--out {file}/m cannot be created"),
    _case("bench-out-under-file", "bench paper --quick --seeds 1 --out {file}/r", "--out {file}/r cannot be created"),
    _case("carry-to-under-file", "bench carry save --out {empty} --to {file}/c", "--to {file}/c cannot be created"),
    _case("info-missing", "data info {missing}", "{missing}"),
    _case("info-bad-json", "data info {badjson}", "{badjson}/manifest.json"),
    _case("generate-episodes-0", "data generate --out {out} --preset tiny --episodes 0", "--episodes"),
    _case("generate-preset-typo", "data generate --out {out} --preset tiyn --episodes 1", "--preset"),
    _case("generate-exposure-negative", "data generate --out {out} --preset tiny --episodes 1 --exposure-jitter -0.1",
          "--exposure-jitter"),
    _case("generate-texture-scale-order", "data generate --out {out} --preset tiny --episodes 1 --texture-scale 0.5 0.1",
          "--texture-scale"),
    # found by an audit: inf passed the module's own parsers (an OverflowError traceback, or a message naming
    # the record instead of the flag), and a huge --views was killed by the kernel without a word
    _case("generate-shard-mb-inf", "data generate --out {out} --preset tiny --episodes 1 --shard-mb inf", "--shard-mb"),
    _case("generate-noise-inf", "data generate --out {out} --preset tiny --episodes 1 --noise inf", "--noise"),
    _case("generate-texture-scale-inf", "data generate --out {out} --preset tiny --episodes 1 --texture-scale 0.1 inf",
          "--texture-scale"),
    _case("generate-views-huge", "data generate --out {out} --preset tiny --episodes 1 --views 100000000", "--views 100000000"),
    # stream: ranges in argparse (was: --rate 0 a ValueError traceback, --frames -3 / --count 0 exit 0);
    # a bad preset or --view and an unreachable zenoh endpoint were tracebacks
    _case("bridge-bundle-without-flow", "stream bridge --bundle {bundle} --duration 1",
          "--bundle {bundle} (version"),   # was: named by its version string only
    _case("camera-rate-0", "stream camera --camera-id c --synthetic --rate 0", "--rate"),
    _case("camera-rate-tiny", "stream camera --camera-id c --synthetic --rate 1e-300", "--rate"),   # was an OverflowError
    _case("bridge-frame-dt-tiny", "stream bridge --bundle {bundle} --frame-dt 1e-300", "--frame-dt"),
    _case("camera-capture-dt-tiny", "stream camera --camera-id c --synthetic --capture-dt 1e-9", "--capture-dt"),
    _case("bridge-id-not-a-key-chunk", "stream bridge --bundle {bundle} --bridge-id a?b", "--bridge-id 'a?b'"),
    _case("bridge-min-score-nan", "stream bridge --bundle {bundle} --min-score nan", "--min-score"),  # dropped every box
    _case("bridge-min-score-2", "stream bridge --bundle {bundle} --min-score 2", "--min-score"),
    _case("camera-frames-negative", "stream camera --camera-id c --synthetic --frames -3", "--frames"),
    _case("camera-episode-frames-0", "stream camera --camera-id c --synthetic --episode-frames 0", "--episode-frames"),
    _case("listen-count-0", "stream listen --count 0", "--count"),
    _case("listen-timeout-negative", "stream listen --timeout -1", "--timeout"),
    _case("camera-view-out-of-range", "stream camera --camera-id c --data {data} --view 9 --wait-for-bridge 0",
          "--view 9"),
    _case("camera-preset-typo", "stream camera --camera-id c --synthetic --preset tinny --frames 1", "tinny"),
    # train: --input-views 0 / 9 and --object-store-mb 0 trained and exited 0
    _case("train-lr-inf", "train occupancy --data {data} --run-dir {out}/r10 --lr inf", "--lr"),
    _case("train-gpus-nan", "train pretrain --data {data} --run-dir {out}/r11 --gpus-per-worker nan", "--gpus-per-worker"),
    _case("train-warp-weight-negative", "train flow --data {data} --run-dir {out}/r12 --warp-weight -1", "--warp-weight"),
    _case("train-input-views-0", "train occupancy --data {data} --run-dir {out}/r1 --input-views 0", "--input-views"),
    _case("train-input-views-9", "train occupancy --data {data} --run-dir {out}/r2 --input-views 9",
          "--input-views 9"),
    _case("train-object-store-0", "train pretrain --data {data} --run-dir {out}/r3 --workers 0 --object-store-mb 0",
          "--object-store-mb"),
    _case("train-data-bad-json", "train pretrain --data {badjson} --run-dir {out}/r5 --workers 0",
          "{badjson}/manifest.json"),
    _case("train-shift-positives-regression",
          "train pretrain --data {data} --run-dir {out}/r6s --workers 0 --objective regression --shift-positives 2",
          "--shift-positives needs --objective contrastive"),
    _case("train-local-negatives-regression",
          "train pretrain --data {data} --run-dir {out}/r6 --workers 0 --objective regression --local-negatives 1",
          "--local-negatives needs --objective contrastive"),
    _case("train-local-negative-radius-0",
          "train pretrain --data {data} --run-dir {out}/r7 --workers 0 --local-negatives 1 --local-negative-radius 0",
          "--local-negative-radius"),
    # a later label draw: --labels-from alone means nothing; a range past the dataset's 2 records is named
    _case("train-labels-from-without-labels", "train detector --data {data} --run-dir {out}/r8 --labels-from 1",
          "--labels-from I needs --labels N"),
    _case("train-labels-from-past-end", "train detector --data {data} --run-dir {out}/r9 --labels 2 --labels-from 1",
          "records [1, 3) are not all in"),
    # jobs / bundle / bench: already one-line errors; kept so that they stay so
    _case("jobs-no-address", "jobs list", "--address"),
    _case("jobs-address-nothing", "jobs status raysubmit_x --address http://127.0.0.1:9", "http://127.0.0.1:9",
          slow=True),
    _case("bundle-truncated-weights", "bundle info {truncated_bundle}", "weights.safetensors"),
    _case("bench-seeds-0", "bench paper --preset tiny --out {out}/b --seeds 0", "--seeds"),
    _case("bench-parallel-seeds-0", "bench paper --preset tiny --out {out}/b --parallel-seeds 0", "--parallel-seeds"),
    _case("bench-label-draws-too-many", "bench paper --preset tiny --out {out}/b --label-draws 30",
          "label_draws 30 at the smallest label budget 2"),
    # amodal boxes: a size prior is three positive lengths, or auto / none for eval moving
    _case("bridge-size-prior-two", "stream bridge --bundle {bundle} --size-prior 4 2", "--size-prior"),
    _case("bridge-size-prior-negative", "stream bridge --bundle {bundle} --size-prior 4 2 -1", "--size-prior"),
    _case("bridge-ground-y-without-level", "stream bridge --bundle {bundle} --ground-y 2", "add --level"),
    _case("bridge-level-ahead-negative", "stream bridge --bundle {bundle} --level --level-ahead -3", "--level-ahead"),
    _case("eval-moving-size-prior-word", "eval moving --data {data} --bundle {bundle} --out {out}/e5 --device cpu "
          "--size-prior big", "--size-prior"),
    # eval: a dataset of another preset than the bundle's was evaluated (exit 0); --per-example 0 was a
    # reshape traceback; --query-views 9 silently meant view 0 (9 % V)
    _case("eval-wrong-preset", "eval occupancy --data {small_data} --bundle {bundle} --out {out}/e1 --device cpu",
          "preset 'small'"),
    _case("eval-lacks-module", "eval detection --data {data} --bundle {bundle} --out {out}/e2 --device cpu",
          "lacks module(s) ['detector']"),
    _case("eval-per-example-0", "eval retrieval --data {data} --bundle {bundle} --out {out}/e3 --per-example 0",
          "--per-example"),
    _case("eval-query-view-range", "eval retrieval --data {data} --bundle {bundle} --out {out}/e4 --device cpu "
          "--query-views 9", "--query-views 9"),
    _case("listen-connect-nothing", "stream listen --mode client --connect tcp/127.0.0.1:9 --timeout 5",
          "tcp/127.0.0.1:9", slow=True),
]


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> dict[str, str]:
    """Paths the cases refer to: a 2-record tiny dataset, bundles, and broken look-alikes."""
    import torch

    from core.bundle import save_bundle
    from core.data.shards import write_dataset
    from core.presets import TINY
    from core.synthetic import generate_record
    from core.tasks.occupancy import OccupancyTask

    root = tmp_path_factory.mktemp("bad_inputs")
    records = [generate_record(TINY, seed=s) for s in (0, 1)]
    write_dataset(root / "data", records, split="val", preset_name="tiny", grid=TINY.grid.to_dict(),
                  generator={"source": "test"}, seed=0, shard_bytes=1 << 30)
    # the manifest names the preset; its records are never read (the check comes first)
    write_dataset(root / "small_data", records[:1], split="val", preset_name="small", grid=TINY.grid.to_dict(),
                  generator={"source": "test"}, seed=0, shard_bytes=1 << 30)
    torch.manual_seed(0)
    task = OccupancyTask.from_preset(TINY)
    save_bundle(root / "bundle", modules={"mapper": task.mapper, "occupancy": task.occupancy}, preset=TINY,
                provenance={"test": "bad inputs"}, metrics={})
    (root / "truncated_bundle").mkdir()
    (root / "truncated_bundle" / "bundle.json").write_text((root / "bundle" / "bundle.json").read_text())
    weights = (root / "bundle" / "weights.safetensors").read_bytes()
    (root / "truncated_bundle" / "weights.safetensors").write_bytes(weights[:len(weights) // 2])
    (root / "file.txt").write_text("not a directory\n")
    (root / "empty").mkdir()
    (root / "badjson").mkdir()
    (root / "badjson" / "manifest.json").write_text('{"format": "n3dmap-sh')
    (root / "noshard").mkdir()
    (root / "noshard" / "manifest.json").write_text((root / "data" / "manifest.json").read_text())
    return {"data": str(root / "data"), "bundle": str(root / "bundle"), "file": str(root / "file.txt"),
            "missing": str(root / "missing"), "empty": str(root / "empty"), "badjson": str(root / "badjson"),
            "noshard": str(root / "noshard"), "small_data": str(root / "small_data"),
            "truncated_bundle": str(root / "truncated_bundle"), "out": str(root / "out")}


@pytest.fixture()
def taken_port():
    """A port held open (listening) for the length of one case."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen(1)
        yield held.getsockname()[1]


@pytest.mark.parametrize("argv, names", CASES)
def test_bad_input_is_one_line_error(argv: str, names: str, fixtures, taken_port) -> None:
    values = dict(fixtures, taken=str(taken_port))
    args = [part.format(**values) for part in argv.split()]
    proc = subprocess.run([sys.executable, "-m", "services.cli.main", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=60, env={**_env(), "RAY_ADDRESS": ""})
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, f"exit {proc.returncode}; stderr:\n{proc.stderr}"
    assert "Traceback" not in proc.stderr, proc.stderr
    assert lines, "no error message on stderr"
    command = args[0]
    assert lines[-1].startswith(f"n3dmap {command}") and ": error: " in lines[-1], lines[-1]
    assert names.format(**values) in lines[-1], lines[-1]


def _env() -> dict[str, str]:
    import os

    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
