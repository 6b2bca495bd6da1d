"""Hostile and faulty inputs, round three: each row of the report, reproduced, refused in one
line that names the file and the key (exit 2), nothing lost or written where it should not be."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from sagonline.apps.cli import main
from tests.fixtures import ROOT, compose_config, llff_scene, own_scene, write_colmap_text


def bomb_png(path: Path, width: int, height: int) -> Path:
    """A 1-bit PNG of width x height zeros: tens of kilobytes holding hundreds of millions of
    pixels once decoded."""
    import struct

    rows = b"".join(b"\x00" + b"\x00" * ((width + 7) // 8) for _ in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows, 9))
        + chunk(b"IEND", b"")
    )
    return path


def user_scene(folder: Path, views: int = 4, width: int = 40, height: int = 30):
    """`own_scene`'s folder, its point_cloud.ply, cameras and first view's ground truth."""
    folder, _, cams, gt = own_scene(folder, views=views, width=width, height=height)
    return folder, folder / "point_cloud.ply", cams, gt


def one_error_line(err: str, *words: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err and "a bug" not in err, err
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


def run_python(*args: str, cwd=ROOT, env=None) -> tuple[int, str, int]:
    """A subprocess: its exit status, stderr, and its peak resident memory in MB (VmHWM: its own
    address space's; ru_maxrss carries over the forking pytest's peak across exec)."""
    code = (
        "import runpy, sys\n"
        f"sys.argv = {list(args)!r}\n"
        "try:\n"
        "    runpy.run_module(sys.argv[0], run_name='__main__', alter_sys=True)\n"
        "finally:\n"
        "    hwm = [ln for ln in open('/proc/self/status') if ln.startswith('VmHWM:')]\n"
        "    peak = int(hwm[0].split()[1]) // 1024 if hwm else -1\n"
        "    print(f'PEAK_MB {peak}', file=sys.stderr)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300, env=env
    )
    lines = proc.stderr.strip().splitlines()
    peak = int(lines[-1].split()[1]) if lines and lines[-1].startswith("PEAK_MB") else -1
    return proc.returncode, "\n".join(lines[:-1]), peak


# --- 1. decompression bombs ---------------------------------------------------------------------


def test_a_png_bomb_is_refused_from_its_header_at_little_memory(tmp_path):
    """A 93 KB PNG of 32000x24000 1-bit pixels cost 42 s and 9.3 GB of memory to score."""
    gt = tmp_path / "gt" / "s"
    pred = tmp_path / "pred" / "s"
    gt.mkdir(parents=True)
    pred.mkdir(parents=True)
    cv2.imwrite(str(gt / "v.png"), np.zeros((30, 40), np.uint8))
    bomb_png(pred / "v.png", 32000, 24000)
    assert (pred / "v.png").stat().st_size < 200_000
    code, err, peak = run_python("sagonline", "score", str(tmp_path / "pred"), str(tmp_path / "gt"))
    assert code == 2, err
    one_error_line(err, "v.png", "exceeds the ceiling", "refused before decoding")
    assert 0 < peak < 1500, peak  # torch and the libraries alone are about 500 MB


def test_a_mask_bomb_given_to_segment_is_refused_at_the_view_size(tmp_path, capsys):
    folder, scene, cams, _ = user_scene(tmp_path / "scene", 4, 40, 30)
    bomb = bomb_png(tmp_path / "mask.png", 20000, 20000)
    code = main(
        [
            "segment",
            str(scene),
            "--cameras",
            str(folder / "transforms.json"),
            "--mask",
            f"0:{bomb}",
            "--out",
            str(tmp_path / "out"),
        ]
    )
    assert code == 2
    one_error_line(capsys.readouterr().err, "mask.png", "exceeds the ceiling of 1,200 for")
    assert not (tmp_path / "out").exists()


# --- 2. the compiled kernels ------------------------------------------------------------------


def test_a_truncated_kernel_library_is_built_again_not_loaded(tmp_path):
    """A truncated library in the kernels folder killed every later render with SIGBUS and no
    word: its bytes are checked against the digest its finished build recorded, and a library
    that differs is removed and built again before anything loads it."""
    from sagonline.render.kernels import build_once, library_digest

    folder, said, built = tmp_path / "kernels" / "build", [], []

    def build():  # stands in for torch's loader: compiles when the library is absent
        library = folder / "k.so"
        built.append(library.exists())
        if not library.exists():
            library.write_bytes(b"\x7fELF" + b"\x00" * 8000)
        return library.read_bytes()

    build_once(folder, "k", build, say=said.append)  # a first build records its digest
    good = (folder / "k.so").read_bytes()
    assert (folder / "k.so.sha256").read_text().strip() == library_digest(folder / "k.so")
    (folder / "k.so").write_bytes(good[:4096])  # a build killed while linking
    assert build_once(folder, "k", build, say=said.append) == good
    assert built == [False, False]  # the truncated library was never handed to the loader
    assert any("not the build that finished (its bytes changed)" in s for s in said), said
    build_once(folder, "k", build, say=said.append)  # an intact library is loaded as it is
    assert built == [False, False, True]


# --- 5. recorded prompts ------------------------------------------------------------------------


@pytest.fixture
def masked_segmentation(tmp_path, monkeypatch):
    """A segmentation made from a mask given by a path relative to the folder it was run in."""
    folder, scene, cams, gt = user_scene(tmp_path / "scene", 4, 40, 30)
    work = tmp_path / "work"
    work.mkdir()
    cv2.imwrite(str(work / "obj.png"), (gt > 0).astype(np.uint8) * 255)
    monkeypatch.chdir(work)
    argv = [
        "segment",
        str(scene),
        "--cameras",
        str(folder / "transforms.json"),
        "--mask",
        "0:obj.png",
        "--out",
        str(tmp_path / "seg"),
        "--no-record",
    ]
    assert main(argv) == 0
    return tmp_path, scene, folder


def test_a_recorded_mask_is_found_from_labels_json_and_checked(
    masked_segmentation, monkeypatch, capsys
):
    """The mask path is recorded relative to labels.json with its SHA-256: a replay from
    another folder that holds another obj.png uses the recorded file (it used the other one),
    and a changed file is refused."""
    tmp, scene, folder = masked_segmentation
    record = json.loads((tmp / "seg" / "labels.json").read_text())
    obj = record["prompt"]["objects"][0]
    assert obj["mask"] == "../work/obj.png" and len(obj["mask_digest"]) == 32
    elsewhere = tmp / "elsewhere"
    elsewhere.mkdir()
    cv2.imwrite(str(elsewhere / "obj.png"), np.zeros((30, 40), np.uint8))
    monkeypatch.chdir(elsewhere)
    assert (
        main(
            [
                "segment",
                str(scene),
                "--prompts",
                str(tmp / "seg" / "labels.json"),
                "--out",
                str(tmp / "again"),
                "--no-record",
            ]
        )
        == 0
    )
    assert np.array_equal(
        np.load(tmp / "again" / "labels.npy"), np.load(tmp / "seg" / "labels.npy")
    )
    capsys.readouterr()
    cv2.imwrite(str(tmp / "work" / "obj.png"), np.zeros((30, 40), np.uint8))  # changed
    assert (
        main(
            [
                "segment",
                str(scene),
                "--prompts",
                str(tmp / "seg" / "labels.json"),
                "--out",
                str(tmp / "third"),
            ]
        )
        == 2
    )
    one_error_line(
        capsys.readouterr().err,
        "labels.json",
        "prompt.objects[0].mask",
        "not the file that was recorded",
    )


def test_a_labels_json_of_another_scene_is_said(masked_segmentation, capsys):
    tmp, scene, folder = masked_segmentation
    other = tmp / "other.ply"
    data = bytearray(scene.read_bytes())
    data[-1] ^= 1  # another scene (one value's last bit)
    other.write_bytes(bytes(data))
    assert (
        main(
            [
                "segment",
                str(other),
                "--prompts",
                str(tmp / "seg" / "labels.json"),
                "--out",
                str(tmp / "on_other"),
                "--no-record",
            ]
        )
        == 0
    )
    assert "was recorded on another scene" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda r: r["vote"].update(eps="0.5"), ["vote.eps must be int or float", "'0.5'"]),
        (lambda r: r.update(orbit="abc"), ["orbit must be int", "'abc'"]),
        (
            lambda r: r["prompt"]["objects"][0].update(clicks=[[1, "x"]]),
            ["prompt.objects[0].clicks[0]"],
        ),
        (lambda r: r["prompt"].update(objects="chair"), ["prompt.objects must be list"]),
        (lambda r: r["prompt"].update(view_name=None), ["prompt.view_name must be str"]),
    ],
)
def test_a_bad_prompts_field_is_named(masked_segmentation, capsys, edit, words):
    """A wrong type in a labels.json crashed (vote.eps "0.5", orbit "abc"); errors about its
    clicks named a --click the user never typed."""
    tmp, scene, _ = masked_segmentation
    record = json.loads((tmp / "seg" / "labels.json").read_text())
    edit(record)
    bad = tmp / "seg" / "bad.json"  # beside labels.json: the recorded mask path holds
    bad.write_text(json.dumps(record))
    assert main(["segment", str(scene), "--prompts", str(bad), "--out", str(tmp / "o")]) == 2
    line = one_error_line(capsys.readouterr().err, "bad.json", *words)
    assert "--click" not in line


def test_a_recorded_click_outside_its_view_is_named_by_its_field(masked_segmentation, capsys):
    tmp, scene, _ = masked_segmentation
    record = json.loads((tmp / "seg" / "labels.json").read_text())
    record["prompt"]["objects"][0]["clicks"] = [[500.0, 10.0]]
    bad = tmp / "seg" / "far.json"
    bad.write_text(json.dumps(record))
    assert main(["segment", str(scene), "--prompts", str(bad), "--out", str(tmp / "o")]) == 2
    one_error_line(capsys.readouterr().err, "far.json: prompt.objects[0].clicks[0]", "outside")


# --- 6. sagonline score ------------------------------------------------------------------------


def _label_folders(tmp_path: Path) -> tuple[Path, Path]:
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    for folder in (gt / "s", pred / "s"):
        folder.mkdir(parents=True)
        cv2.imwrite(str(folder / "v.png"), np.eye(8, dtype=np.uint8))
    return pred, gt


def score(*argv: str) -> tuple[int, str, str]:
    import contextlib
    import io

    from sagonline.apps.cli.score import main as score_main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            score_main(list(argv))
            code = 0
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


def test_score_digests_what_it_scored_through_a_linked_scene_folder(tmp_path):
    """A scene folder that is a symbolic link was scored but left out of the SHA-256 (the
    digest of empty input beside mIoU 100)."""
    pred, gt = _label_folders(tmp_path)
    real = tmp_path / "elsewhere"
    (pred / "s").rename(real)
    (pred / "s").symlink_to(real, target_is_directory=True)
    code, out, _ = score(str(pred), str(gt))
    assert code == 0
    empty = "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
    assert empty not in out and "overall mIoU 100.00" in out


def test_score_refuses_the_ground_truth_as_predictions_and_names_extras(tmp_path):
    pred, gt = _label_folders(tmp_path)
    code, _, err = score(str(gt), str(gt))
    assert code == 2 and "is the ground truth folder" in err
    cv2.imwrite(str(pred / "s" / "extra.png"), np.zeros((8, 8), np.uint8))
    (pred / "t").mkdir()
    cv2.imwrite(str(pred / "t" / "w.png"), np.zeros((8, 8), np.uint8))
    code, out, _ = score(str(pred), str(gt))
    assert code == 0 and "2 prediction(s) have no ground truth" in out and "t/w.png" in out
    code, _, err = score(str(pred), str(gt), "--ignore", "-1")
    assert code == 2 and "--ignore -1: a label id in [0, 65535]" in err


# --- 7. sagonline figure ------------------------------------------------------------------------


@pytest.fixture
def segment_folder(tmp_path):
    folder, scene, cams, gt = user_scene(tmp_path / "scene", 4, 40, 30)
    ys, xs = np.nonzero(gt)
    click = f"0:{xs[len(xs) // 2] + 0.5},{ys[len(xs) // 2] + 0.5}"
    assert (
        main(
            [
                "segment",
                str(scene),
                "--cameras",
                str(folder / "transforms.json"),
                "--click",
                click,
                "--out",
                str(tmp_path / "seg"),
                "--no-record",
            ]
        )
        == 0
    )
    return tmp_path, tmp_path / "seg", scene


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda r: [1, 2], ["holds a list"]),
        (lambda r: {k: v for k, v in r.items() if k != "scene"}, ["scene must name"]),
        (lambda r: {**r, "names": ["background"]}, ["ids must lie in [0, 1)"]),
    ],
)
def test_figure_refuses_a_labels_json_it_cannot_trust(segment_folder, capsys, edit, words):
    tmp, seg, _ = segment_folder
    path = seg / "labels.json"
    path.write_text(json.dumps(edit(json.loads(path.read_text()))))
    assert main(["figure", str(seg), "--out", str(tmp / "f.png")]) == 2
    one_error_line(capsys.readouterr().err, *words)


def test_figure_refuses_another_scene_and_a_label_png_of_another_size(segment_folder, capsys):
    tmp, seg, scene = segment_folder
    record = json.loads((seg / "labels.json").read_text())
    from sagonline.scene.io import read_scene, write_ply

    other = tmp / "other.ply"
    write_ply(other, read_scene(scene).subset(np.arange(100)))
    (seg / "labels.json").write_text(json.dumps({**record, "scene": str(other)}))
    assert main(["figure", str(seg), "--out", str(tmp / "f.png")]) == 2
    one_error_line(capsys.readouterr().err, "not the file the labels were made on")
    (seg / "labels.json").write_text(json.dumps(record))
    png = next((seg / "views").glob("0000_*_labels.png"))
    cv2.imwrite(str(png), np.zeros((1, 1), np.uint8))
    assert main(["figure", str(seg), "--out", str(tmp / "f.png")]) == 2
    one_error_line(capsys.readouterr().err, "1x1, but view 0 renders at 40x30")


# --- 9. plug-ins --------------------------------------------------------------------------------


def test_a_plugin_that_raises_at_import_is_named(tmp_path):
    (tmp_path / "broken_plugin.py").write_text("raise RuntimeError('the plug-in is broken')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "SAGONLINE_PLUGINS": "broken_plugin"}
    for command in (["sagonline", "plugins"], ["bench.runners.eval", "record=false"]):
        code, err, _ = run_python(*command, env=env)
        assert code == 2, (command, err)
        one_error_line(err, "'broken_plugin'", "RuntimeError: the plug-in is broken")
    env["SAGONLINE_PLUGINS"] = "../x"
    code, err, _ = run_python("sagonline", "plugins", env=env)
    assert code == 2
    one_error_line(err, "'../x': not a module name")


def test_a_plugin_taking_a_registered_name_is_named_with_its_module(tmp_path):
    (tmp_path / "thief.py").write_text(
        "from dataclasses import dataclass\n"
        "from sagonline.core.plugins import SEGMENTERS\n"
        "@dataclass\nclass C:\n    pass\n"
        "@SEGMENTERS.register('classical', C)\nclass Mine:\n    pass\n"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "SAGONLINE_PLUGINS": "thief"}
    code, err, _ = run_python("sagonline", "plugins", env=env)
    assert code == 2
    one_error_line(err, "'classical' is registered twice", "sagonline.segment.classical", "thief")


# --- 8, 10, 11. datasets, captures and the rest --------------------------------------------------


def test_a_dataset_name_that_is_a_path_is_refused(tmp_path):
    code, err, _ = run_python(
        "bench.runners.eval", "dataset.name=../../../x", f"hydra.run.dir={tmp_path}/run"
    )
    assert code == 2
    one_error_line(err, "dataset.name='../../../x'", "not a path")
    assert not (tmp_path / "run").exists()


NAMES = [f"IMG_{i:04d}" for i in range(6)]


def _capture(root: Path) -> Path:
    """A capture in the layout of the shared ones: images_4/, masks_4/, poses_bounds.npy, and a
    fitted scene."""
    from tests.fixtures import object_mask, write_image

    cams, scene = llff_scene(root / "cap", NAMES)
    for cam in cams:
        write_image(
            root / "cap" / "masks_4" / f"{cam.name}.png",
            (object_mask(scene, cam) > 0).astype(np.uint8) * 255,
        )
    return root / "cap"


def _eval_capture(root: Path, *extra: str):
    from bench.runners.eval import evaluate

    cfg = compose_config(
        "eval",
        "dataset=mold_cape",
        f"dataset.root={root}",
        "dataset.name=cap",
        "record=false",
        "progress=false",
        *extra,
    )
    return evaluate(cfg, root.parent / "run")


@pytest.mark.slow
def test_a_capture_that_changed_is_refused_not_regrouped(tmp_path, capsys):
    """A missing photograph moved views between the photographed and mask-only groups without
    a word; a mask at half size was scored at its own size; a photograph that is not an image
    ended in a traceback."""
    cap = _capture(tmp_path)
    photos = f"dataset.adapter.expected_photos={len(NAMES)}"
    (cap / "images_4" / f"{NAMES[2]}.JPG").unlink()
    with pytest.raises(SystemExit):
        _eval_capture(cap, photos)
    assert "5 photographs of the scene's views, the protocol expects 6" in capsys.readouterr().err
    cv2.imwrite(str(cap / "images_4" / f"{NAMES[2]}.JPG"), np.full((24, 32, 3), 90, np.uint8))
    half = cv2.imread(str(cap / "masks_4" / f"{NAMES[3]}.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(cap / "masks_4" / f"{NAMES[3]}.png"), half[::2, ::2])
    with pytest.raises(SystemExit):
        _eval_capture(cap, photos)
    assert "16x12, but the scene's other masks are 32x24" in capsys.readouterr().err


def test_a_photograph_that_is_not_an_image_is_named(tmp_path):
    from sagonline.datasets.common import scene_cameras
    from sagonline.scene.io.images import ImageFileError

    cap = _capture(tmp_path)
    for p in (cap / "images_4").iterdir():
        p.write_bytes(b"not an image")
    with pytest.raises(ImageFileError, match="IMG_0000.JPG: not a readable image"):
        scene_cameras(cap, "images_4")


def test_a_truncated_photograph_is_refused_by_the_fit(tmp_path):
    from sagonline.scene.io.images import ImageFileError, read_rgb

    photo = tmp_path / "p.jpg"
    cv2.imwrite(str(photo), np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8))
    photo.write_bytes(photo.read_bytes()[:-300])
    with pytest.raises(ImageFileError, match="p.jpg: a damaged or truncated image"):
        read_rgb(photo)


def test_the_small_refusals_say_what_to_do(tmp_path, capsys):
    folder, scene, cams, gt = user_scene(tmp_path / "scene", 4, 40, 30)
    base = [
        "segment",
        str(scene),
        "--cameras",
        str(folder / "transforms.json"),
        "--out",
        str(tmp_path / "o"),
    ]
    assert main([*base, "--click", "0:20,12:neg"]) == 2
    one_error_line(capsys.readouterr().err, "a negative click says what an object is not")
    assert main([*base, "--click", "-1:10,10"]) == 2
    one_error_line(capsys.readouterr().err, "view -1 is out of range")
    assert main([*base, "--click", "0:20,12", "--eps", "nan"]) == 2
    line = one_error_line(capsys.readouterr().err, "--eps nan")
    assert "consensus.eps" not in line
    assert main(["export", str(scene)]) == 2
    one_error_line(capsys.readouterr().err, "a file; export takes a finished evaluation's run")
    empty = tmp_path / "colmap"
    write_colmap_text(empty, [])
    assert main(["cameras", str(empty)]) == 2
    one_error_line(capsys.readouterr().err, "holds no cameras")


def test_a_view_that_shows_nothing_and_an_extreme_opacity(tmp_path, capsys):
    import warnings

    from plyfile import PlyData

    folder, scene, cams, _ = user_scene(tmp_path / "scene", 4, 40, 30)
    data = PlyData.read(str(scene))
    data["vertex"].data["opacity"][0] = -1e30
    data.write(str(tmp_path / "extreme.ply"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's overflow warning with a source line, no more
        assert main(["info", str(tmp_path / "extreme.ply")]) == 0
    behind = json.loads((folder / "transforms.json").read_text())
    for frame in behind["frames"]:
        frame["transform_matrix"][0][3] += 1e4  # every camera far away, looking at nothing
    (tmp_path / "away.json").write_text(json.dumps(behind))
    assert (
        main(
            [
                "render",
                str(scene),
                "--cameras",
                str(tmp_path / "away.json"),
                "--out",
                str(tmp_path / "v.png"),
            ]
        )
        == 0
    )
    assert "shows almost nothing of the scene" in capsys.readouterr().err


def test_a_dataset_root_that_is_a_file_and_a_setting_of_another_command(tmp_path):
    (tmp_path / "f").write_text("")
    code, err, _ = run_python(
        "bench.runners.eval",
        "dataset=generic",
        f"dataset.root={tmp_path / 'f'}",
        f"hydra.run.dir={tmp_path}/run",
        "record=false",
    )
    assert code == 2 and "is a file; it names the folder that holds the scenes" in err
    code, err, _ = run_python("bench.runners.eval", "finish=true")
    assert code == 2
    one_error_line(err, "no setting 'finish'", "bench.runners.scenes")
    env = {**os.environ, "SAGONLINE_KERNEL_DIR": str(tmp_path / "f")}
    code, err, _ = run_python(
        "sagonline", "render", "nothing.ply", "--out", "x.png", "--backend", "native", env=env
    )
    assert code == 2 and "a bug" not in err


def test_memory_of_the_test_process_is_bounded():
    """The hostile files above were refused before their pixels were decoded: this process
    never grew past a few gigabytes."""
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss < 6 * 1024 * 1024
