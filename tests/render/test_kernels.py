"""Building the CPU kernels: once per environment, said out loud, never an endless wait on a
build that was killed (the build itself is stood in for by a function)."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from sagonline.render.kernels import build_once, kernel_root


def test_the_kernels_live_in_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("SAGONLINE_KERNEL_DIR", raising=False)
    assert kernel_root().is_relative_to(sys.prefix)  # two checkouts, two environments, two builds
    monkeypatch.setenv("SAGONLINE_KERNEL_DIR", str(tmp_path))
    assert kernel_root() == tmp_path


def test_a_first_build_says_so_and_a_second_does_not(tmp_path):
    said, built = [], []

    def build():
        built.append(1)
        (tmp_path / "k" / "ext.so").write_bytes(b"")
        return "module"

    assert build_once(tmp_path / "k", "ext", build, said.append) == "module"
    assert any("compiling the CPU kernels, one time" in s for s in said)
    said.clear()
    assert build_once(tmp_path / "k", "ext", build, said.append) == "module"
    assert said == [] and len(built) == 2  # torch's loader finds its build and loads it


def test_a_lock_left_by_a_killed_build_is_cleared(tmp_path):
    """A build killed midway leaves torch's `lock` file; its owner is gone (our own lock is
    free), so the next run removes it and goes on instead of waiting forever."""
    said = []
    (tmp_path / "k").mkdir()
    (tmp_path / "k" / "lock").write_text("")

    def build():
        assert not (tmp_path / "k" / "lock").exists()
        return "module"

    assert build_once(tmp_path / "k", "ext", build, said.append) == "module"
    assert any("killed before it finished" in s for s in said)


def test_a_second_process_waits_for_a_live_build_and_says_so(tmp_path):
    (tmp_path / "k").mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, os, sys\n"
            f"fd = os.open({str(tmp_path / 'ext.build-lock')!r}, os.O_RDWR | os.O_CREAT)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX)\nprint('holding', flush=True)\nsys.stdin.readline()\n",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert holder.stdout.readline().strip() == "holding"
    said, waiting, result = [], threading.Event(), []

    def say(text):
        said.append(text)
        if text.startswith("waiting"):
            waiting.set()

    worker = threading.Thread(
        target=lambda: result.append(build_once(tmp_path / "k", "ext", lambda: "module", say))
    )
    worker.start()
    assert waiting.wait(60)  # the worker is blocked on the live builder's lock and said so
    assert result == []
    holder.communicate("done\n", timeout=60)  # the live build ends
    worker.join(60)
    assert not worker.is_alive()
    assert result == ["module"] and said[0].startswith("waiting for another process")


def test_a_library_that_is_not_the_finished_build_is_built_again(tmp_path):
    """A build killed while linking (or a full disk) leaves a truncated library that would kill
    every later process with SIGBUS: its bytes no longer match the digest recorded when its
    build finished, so the folder is emptied, the reason said, and the kernels built again."""
    said, built = [], []
    k = tmp_path / "k"

    def build():
        library = k / "ext.so"
        built.append(library.exists())  # torch's loader would only load it if it exists
        if not library.exists():
            library.write_bytes(b"\x7fELF" + b"\0" * 4096)
        return "module"

    assert build_once(k, "ext", build, said.append) == "module"
    assert (k / "ext.so.sha256").is_file()
    assert build_once(k, "ext", build, said.append) == "module"
    assert built == [False, True]  # the recorded build is loaded as it is
    (k / "ext.so").write_bytes(b"\x7fELF" + b"\0" * 100)  # truncated
    (k / "ext.o").write_bytes(b"object")
    said.clear()
    assert build_once(k, "ext", build, said.append) == "module"
    assert built[-1] is False and not (k / "ext.o").exists()
    assert any("not the build that finished (its bytes changed)" in s for s in said)
    (k / "ext.so.sha256").unlink()  # a build from before digests were recorded
    said.clear()
    build_once(k, "ext", build, said.append)
    assert any("no digest was recorded" in s for s in said) and built[-1] is False


def test_a_long_build_says_that_it_still_compiles(tmp_path):
    import time

    said = []

    def build():
        time.sleep(0.35)
        (tmp_path / "k" / "ext.so").write_bytes(b"x")
        return "module"

    build_once(tmp_path / "k", "ext", build, said.append, every=0.1)
    assert any(s.startswith("still compiling the CPU kernels") for s in said)


def test_a_kernel_folder_that_is_a_file_is_refused(tmp_path, monkeypatch):
    import pytest

    from sagonline.render.kernels import NativeBuildError

    (tmp_path / "f").write_text("")
    monkeypatch.setenv("SAGONLINE_KERNEL_DIR", str(tmp_path / "f"))
    with pytest.raises(NativeBuildError, match="is a file: it must name a folder"):
        kernel_root()


@pytest.mark.filterwarnings("ignore:'sagonline.render.kernels' found in sys.modules")
def test_the_install_step_builds_them_and_names_a_place_it_cannot_use(
    tmp_path, monkeypatch, capsys
):
    """`python -m sagonline.render.kernels` (`make install`): builds the kernels, or finds them
    built, and says where; a kernel folder that is a file is named, with exit status 1 (the
    Makefile then goes on, and a run tries again)."""
    import runpy

    monkeypatch.delenv("SAGONLINE_KERNEL_DIR", raising=False)
    runpy.run_module("sagonline.render.kernels", run_name="__main__")
    assert f"the CPU kernels are built ({kernel_root()})" in capsys.readouterr().out
    (tmp_path / "f").write_text("")
    monkeypatch.setenv("SAGONLINE_KERNEL_DIR", str(tmp_path / "f"))
    with pytest.raises(SystemExit) as stop:
        runpy.run_module("sagonline.render.kernels", run_name="__main__")
    assert stop.value.code == 1
    assert f"SAGONLINE_KERNEL_DIR={tmp_path / 'f'} is a file" in capsys.readouterr().err


@pytest.mark.parametrize("package", [True, False], ids=["ninja package", "no ninja package"])
def test_the_kernels_build_with_the_environments_ninja_whatever_path_finds_first(
    tmp_path, monkeypatch, package
):
    """torch's loader runs the `ninja` PATH finds: from a shell where the environment is not
    activated, none on a machine without a system ninja (the build failed), or a system one of
    another version, which hashes the same compile command its own way, so the two rebuilt the
    kernels in turn (21 s a switch here). The build runs the environment's own (`ninja`
    package), PATH is put back after it, and without the package PATH is left as it is."""
    import os
    import shutil

    import ninja
    from torch.utils import cpp_extension

    from sagonline.render import kernels

    other = tmp_path / "bin"
    other.mkdir()
    (other / "ninja").write_text("#!/bin/sh\necho 1.11.1\n")
    (other / "ninja").chmod(0o755)
    monkeypatch.setenv("PATH", str(other))
    monkeypatch.setenv("SAGONLINE_KERNEL_DIR", str(tmp_path / "kernels"))
    if not package:
        monkeypatch.setitem(sys.modules, "ninja", None)  # import ninja raises ImportError
    found = []

    def load(**arguments):  # torch's loader: which ninja would it run?
        found.append(shutil.which("ninja"))
        return "module"

    monkeypatch.setattr(cpp_extension, "load", load)
    assert kernels.load_extension.__wrapped__() == "module"
    own = shutil.which("ninja", path=ninja.BIN_DIR)
    assert own is not None and own != str(other / "ninja")
    assert found == [own if package else str(other / "ninja")]
    assert os.environ["PATH"] == str(other)
