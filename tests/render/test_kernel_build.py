"""The compiled kernels: a truncated library is built again, not loaded."""

from __future__ import annotations


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
