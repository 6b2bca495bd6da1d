"""scripts/gsplat_bundle.py: gsplat packed into the GPU bundle here (with the extension `make
gsplat-prebuilt` compiled, or only its sources), unpacked on the GPU machine, and its compiled
extension set aside wherever it cannot serve (another Python or PyTorch, or a failed
rasterisation), so that gsplat compiles its sources instead."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest
import torch

from sagonline.core.provenance import sha256_file

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("gsplat_bundle", ROOT / "scripts/gsplat_bundle.py")
gsplat_bundle = importlib.util.module_from_spec(spec)
spec.loader.exec_module(gsplat_bundle)

MACHINE = {"python": "3.12", "torch": "2.11.0+cu130", "cuda": "13.0"}
EXTENSION = "gsplat/csrc.cpython-312-x86_64-linux-gnu.so"


def a_wheel(folder: Path, version: str = "1.5.3", compiled: bool = True) -> Path:
    """A wheel of gsplat's layout: its package, a CUDA source, its metadata and, where
    `compiled`, its extension."""
    tag = "cp312-cp312-linux_x86_64" if compiled else "py3-none-any"
    wheel = folder / f"gsplat-{version}-{tag}.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        archive.writestr("gsplat/__init__.py", f"__version__ = {version!r}\n")
        archive.writestr("gsplat/cuda/csrc/Projection.cu", "// a CUDA source\n")
        archive.writestr(
            f"gsplat-{version}.dist-info/METADATA", f"Name: gsplat\nVersion: {version}\n"
        )
        archive.writestr("gsplat/__pycache__/__init__.cpython-312.pyc", b"bytecode")
        if compiled:
            archive.writestr(EXTENSION, b"\x7fELF a compiled extension")
    return wheel


def a_prebuilt(folder: Path, version: str = "1.5.3") -> Path:
    """What scripts/prebuild_gsplat.py leaves: a compiled wheel and BUILT_FOR.json."""
    folder.mkdir()
    wheel = a_wheel(folder, version)
    built = {"gsplat": version, "wheel": wheel.name, "sha256": sha256_file(wheel)}
    built |= MACHINE | {"archs": "9.0"}
    (folder / gsplat_bundle.MANIFEST).write_text(json.dumps(built))
    return folder


def test_a_compiled_wheel_is_packed_as_its_installed_files_with_what_it_was_built_for(tmp_path):
    prebuilt = a_prebuilt(tmp_path / "prebuilt")
    (tmp_path / "bundle").mkdir()
    (tmp_path / "bundle" / "gsplat-1.5.2.tar.xz").write_bytes(b"an older version")
    wheel, built = gsplat_bundle.prebuilt_wheel(prebuilt, "1.5.3")
    packed = gsplat_bundle.pack(tmp_path / "bundle", wheel, built, "1.5.3")
    assert packed.name == "gsplat-1.5.3.tar.xz"
    assert sorted(p.name for p in (tmp_path / "bundle").iterdir()) == [
        "gsplat-1.5.3.json",
        "gsplat-1.5.3.tar.xz",
    ]
    with tarfile.open(packed) as tar:
        names = set(tar.getnames())
    assert {EXTENSION, "gsplat/cuda/csrc/Projection.cu", "gsplat/__init__.py"} <= names
    assert not any("__pycache__" in name for name in names)
    record = json.loads((tmp_path / "bundle" / "gsplat-1.5.3.json").read_text())
    assert record["built_for"]["torch"] == "2.11.0+cu130" and record["from"] == wheel.name


def test_a_prebuilt_wheel_of_another_version_is_unused_and_a_changed_one_refused(tmp_path, capsys):
    assert gsplat_bundle.prebuilt_wheel(tmp_path / "nothing", "1.5.3") is None
    prebuilt = a_prebuilt(tmp_path / "prebuilt", version="1.5.2")
    assert gsplat_bundle.prebuilt_wheel(prebuilt, "1.5.3") is None
    assert "holds gsplat 1.5.2, not 1.5.3" in capsys.readouterr().out
    (wheel,) = prebuilt.glob("*.whl")
    wheel.write_bytes(wheel.read_bytes() + b"changed")
    with pytest.raises(SystemExit, match="not the file"):
        gsplat_bundle.prebuilt_wheel(prebuilt, "1.5.2")


def bundled(tmp_path: Path, compiled: bool = True) -> Path:
    bundle = tmp_path / "bundle"
    built = {**MACHINE, "archs": "9.0"} if compiled else None
    gsplat_bundle.pack(bundle, a_wheel(tmp_path, compiled=compiled), built, "1.5.3")
    return bundle


def test_on_the_machine_it_was_built_for_the_extension_is_installed_and_kept(tmp_path):
    site = tmp_path / "site"
    said = gsplat_bundle.install(bundled(tmp_path), site, here=MACHINE)
    assert (site / EXTENSION).exists() and (site / "gsplat/cuda/csrc/Projection.cu").exists()
    assert "with its compiled extension" in said and "compute capability 9.0" in said


@pytest.mark.parametrize(
    ("key", "value"), [("torch", "2.13.0+cpu"), ("python", "3.11"), ("cuda", "12.8")]
)
def test_under_another_python_or_torch_the_extension_is_set_aside_saying_why(
    tmp_path, capsys, key, value
):
    site = tmp_path / "site"
    said = gsplat_bundle.install(bundled(tmp_path), site, here={**MACHINE, key: value})
    assert not (site / EXTENSION).exists()
    assert (site / (EXTENSION + gsplat_bundle.SET_ASIDE)).exists()
    assert f"{key} {MACHINE[key]} (here {value})" in said
    assert "gsplat compiles its sources" in capsys.readouterr().out


def test_a_bundle_of_sources_only_installs_to_compile_on_first_use(tmp_path):
    site = tmp_path / "site"
    said = gsplat_bundle.install(bundled(tmp_path, compiled=False), site, here=MACHINE)
    assert "compiles on first use" in said and (site / "gsplat/__init__.py").exists()


def test_a_bundle_without_one_packed_gsplat_is_refused_naming_it(tmp_path):
    (tmp_path / "bundle").mkdir()
    with pytest.raises(SystemExit, match=r"bundle holds 0 gsplat-\*.tar.xz"):
        gsplat_bundle.install(tmp_path / "bundle", tmp_path / "site")


class Attempts:
    """A stand-in for the rasterisation on CUDA: fails while the compiled extension is in place
    where `broken`, else passes."""

    def __init__(self, broken: bool):
        self.broken, self.calls = broken, 0

    def __call__(self, site: Path) -> tuple[bool, str]:
        self.calls += 1
        if self.broken and (site / EXTENSION).exists():
            return False, "RuntimeError: no kernel image is available for execution on the device"
        return True, "gsplat: one Gaussian rasterised"


def test_an_extension_that_fails_on_the_gpu_is_set_aside_and_the_sources_compiled(tmp_path):
    site = tmp_path / "site"
    gsplat_bundle.install(bundled(tmp_path), site, here=MACHINE)
    attempts = Attempts(broken=True)
    assert gsplat_bundle.ready(site, attempts) and attempts.calls == 2
    assert (site / (EXTENSION + gsplat_bundle.SET_ASIDE)).exists()


def test_a_working_extension_is_tried_once_and_a_failure_without_one_is_final(tmp_path):
    site = tmp_path / "site"
    gsplat_bundle.install(bundled(tmp_path), site, here=MACHINE)
    attempts = Attempts(broken=False)
    assert gsplat_bundle.ready(site, attempts) and attempts.calls == 1
    assert (site / EXTENSION).exists()
    (site / EXTENSION).unlink()
    assert gsplat_bundle.ready(site, lambda s: (False, "no CUDA toolkit")) is False


NO_CUDA = pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")


@NO_CUDA
def test_the_smoke_test_fails_in_a_fresh_process_where_gsplat_cannot_rasterise(tmp_path):
    """`ready`'s own attempt runs `smoke` in a fresh process: here, without CUDA, it fails and
    says why, and nothing crashes the caller."""
    passed, said = gsplat_bundle.attempt(tmp_path)
    assert not passed and said.endswith("gsplat: no CUDA device here to rasterise on")


def test_the_prebuild_refuses_a_python_that_does_not_run_naming_the_setting(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            "scripts/prebuild_gsplat.py",
            "--python",
            "no-such-python3.12",
            "--toolchain",
            str(tmp_path / "toolchain"),
            "--out",
            str(tmp_path / "out"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 1 and "GPU_PYTHON" in done.stderr
    assert not (tmp_path / "out").exists()


@NO_CUDA
def test_ready_without_a_cuda_device_stops_and_sets_nothing_aside(tmp_path):
    """No CUDA device is not the compiled extension's failure: it stays for the GPU."""
    site = tmp_path / "site"
    gsplat_bundle.install(bundled(tmp_path), site, here=MACHINE)
    done = subprocess.run(
        [sys.executable, "scripts/gsplat_bundle.py", "ready", "--site", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 1 and "no CUDA device here" in done.stderr
    assert (site / EXTENSION).exists()


def test_a_truncated_or_unrecorded_bundle_is_refused_naming_the_file(tmp_path):
    bundle = bundled(tmp_path)
    packed = bundle / "gsplat-1.5.3.tar.xz"
    packed.write_bytes(packed.read_bytes()[:200])  # a copy cut short
    with pytest.raises(SystemExit, match=r"gsplat-1\.5\.3\.tar\.xz cannot be unpacked"):
        gsplat_bundle.install(bundle, tmp_path / "site", here=MACHINE)
    (bundle / "gsplat-1.5.3.json").unlink()
    with pytest.raises(SystemExit, match=r"gsplat-1\.5\.3\.json is missing"):
        gsplat_bundle.install(bundle, tmp_path / "site", here=MACHINE)


def test_the_commands_pack_a_prebuilt_wheel_and_install_it(tmp_path):
    """`pack` and `install` as make gpu-bundle and the GPU check call them: the prebuilt wheel
    of the installed gsplat's version packed (no download), then unpacked under this Python,
    for which it was not built, so its extension is set aside."""
    import importlib.metadata

    version = importlib.metadata.version("gsplat")
    prebuilt, bundle, site = (
        a_prebuilt(tmp_path / "prebuilt", version),
        tmp_path / "b",
        tmp_path / "s",
    )
    script = [sys.executable, "scripts/gsplat_bundle.py"]
    packing = [*script, "pack", "--bundle", str(bundle), "--prebuilt", str(prebuilt)]
    said = subprocess.run(packing, cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert "compiled for torch 2.11.0+cu130" in said
    installing = [*script, "install", "--bundle", str(bundle), "--site", str(site)]
    said = subprocess.run(installing, cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert "its compiled extension unused (built for" in said
    assert (site / (EXTENSION + gsplat_bundle.SET_ASIDE)).exists()
