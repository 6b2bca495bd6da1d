"""The library stays readable: no module of sagonline/ over 400 lines, no function over 80 lines
without a reason ("Why one function:") in its docstring, and no import running back up from the
fitting package into the datasets."""

from __future__ import annotations

import ast
import subprocess
import sys

import pytest

from tests.fixtures import ROOT

PACKAGE = ROOT / "sagonline"


def test_no_module_over_400_lines():
    """The library and the harness around it (bench/) alike."""
    long = {
        str(p.relative_to(ROOT)): n
        for p in [*PACKAGE.rglob("*.py"), *(ROOT / "bench").rglob("*.py")]
        if (n := p.read_text().count("\n")) > 400
    }
    assert not long, long


def test_long_functions_say_why():
    silent = []
    for p in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                doc = ast.get_docstring(node) or ""
                if length > 80 and "Why one function:" not in doc:
                    silent.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.name} ({length})")
    assert not silent, silent


@pytest.mark.slow
def test_fitting_does_not_depend_on_the_datasets():
    code = "import sys, sagonline.fitting; print([m for m in sys.modules if 'datasets' in m])"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def _module_imports() -> dict[str, set[str]]:
    """sagonline module -> the sagonline modules it imports (anywhere in it, lazily too)."""
    mods = {}
    for p in PACKAGE.rglob("*.py"):
        name = ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        mods[name] = p

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, p in mods.items():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            for t in targets:
                r = resolve(t) if t.startswith("sagonline") else None
                # a package's own submodules and the top package (which imports nothing) aside
                if r and r not in (m, "sagonline") and not m.startswith(r + "."):
                    graph[m].add(r)
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


# The rooms of sagonline/ in the order the data flows through them (docs/architecture.md): a
# module imports only from its own room and the rooms before it, never one after it.
ROOMS = (
    "core",
    "scene",
    "render",
    "segment",
    "vote",
    "labels",
    "record",
    "score",
    "refine",
    "fitting",
    "datasets",
    "pipeline",
    "apps",
)


def room_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "sagonline"


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    rank = {room: i for i, room in enumerate(ROOMS)}
    found = []
    for module, deps in graph.items():
        src = room_of(module)
        if src in ("sagonline", "__main__"):
            continue
        for dep in deps:
            dst = room_of(dep)
            if dst != src and rank.get(dst, len(ROOMS)) > rank.get(src, -1):
                found.append(f"{module} ({src}) imports {dep} ({dst})")
    return sorted(found)


def test_rooms_follow_the_data_flow():
    graph = _module_imports()
    rooms = {room_of(m) for m in graph} - {"sagonline", "__main__"}
    assert rooms == set(ROOMS), f"rank the new room(s) {sorted(rooms - set(ROOMS))} in ROOMS"
    assert upward_imports(graph) == []
    planted = {"sagonline.scene.views": {"sagonline.apps.cli.segment"}}
    assert upward_imports(planted) == [
        "sagonline.scene.views (scene) imports sagonline.apps.cli.segment (apps)"
    ]


def test_no_import_cycles_and_nothing_imports_the_entry_point():
    graph = _module_imports()
    assert import_cycles(graph) == []
    assert not [m for m, deps in graph.items() if "sagonline.__main__" in deps]
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == [["a", "b", "c"]]


# Every environment variable the library sets, and where: docs/development.md says why.
ENVIRONMENT_WRITES = {
    ("sagonline/__init__.py", "OMP_WAIT_POLICY"),
    ("sagonline/__init__.py", "OPENBLAS_NUM_THREADS"),
    ("sagonline/render/kernels.py", "PATH"),
    ("sagonline/render/triton_vote.py", "TRITON_INTERPRET"),
    ("sagonline/segment/yolo.py", "YOLO_OFFLINE"),
}


def test_the_environment_is_changed_only_where_the_docs_say():
    import re

    found = set()
    for p in PACKAGE.rglob("*.py"):
        for m in re.finditer(r"os\.environ(?:\.setdefault\(|\[)\s*\"(\w+)\"", p.read_text()):
            found.add((str(p.relative_to(ROOT)), m.group(1)))
    assert found == ENVIRONMENT_WRITES
    docs = (ROOT / "docs" / "development.md").read_text()
    assert all(var in docs for _, var in ENVIRONMENT_WRITES)


def test_importing_the_package_first_sets_the_thread_defaults_unless_told():
    """`import sagonline` before numpy and torch: OpenBLAS on one thread and OpenMP's idle
    threads asleep, where the environment says nothing; a value given wins."""
    import os

    script = (
        "import sagonline, os, numpy; "
        "print(os.environ['OPENBLAS_NUM_THREADS'], os.environ['OMP_WAIT_POLICY'])"
    )
    env = {
        k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_WAIT_POLICY")
    }
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert out.stdout.split() == ["1", "PASSIVE"], out.stderr
    env |= {"OPENBLAS_NUM_THREADS": "3", "OMP_WAIT_POLICY": "ACTIVE"}
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert out.stdout.split() == ["3", "ACTIVE"], out.stderr


def test_every_environment_variable_the_code_reads_is_listed_in_the_docs():
    """docs/development.md lists each `SAGONLINE_*` variable that the library, the harness, the
    scripts or the C++ kernels read, and no other."""
    import re

    sources = [*PACKAGE.rglob("*.py"), *PACKAGE.rglob("*.cpp"), *(ROOT / "bench").rglob("*.py")]
    sources += [p for p in (ROOT / "scripts").rglob("*") if p.suffix in (".py", ".sh")]
    read = {m for p in sources for m in re.findall(r"SAGONLINE_[A-Z_]*[A-Z]", p.read_text())}
    docs = (ROOT / "docs" / "development.md").read_text()
    section = docs[docs.index("## Environment variables the harness reads") :]
    section = section[: section.index("\n## ")]
    listed = set(re.findall(r"^\| `(SAGONLINE_[A-Z_]+)`", section, re.M))
    assert read == listed, (sorted(read - listed), sorted(listed - read))


def test_public_functions_say_the_shapes_of_their_tensors():
    """gsplat's habit: every tensor a public function takes or returns has a shape comment on
    its line of the signature (`means: Tensor,  # [N, 3]`)."""
    import re

    shape = re.compile(r"#.*\[")
    silent = []
    for p in PACKAGE.rglob("*.py"):
        lines = p.read_text().splitlines()
        tree = ast.parse("\n".join(lines))
        scopes = [tree] + [n for n in tree.body if isinstance(n, ast.ClassDef)]
        for scope in scopes:
            for node in scope.body:
                if not isinstance(node, ast.FunctionDef) or node.name.startswith("_"):
                    continue
                args = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
                for arg in args:
                    tensor = arg.annotation is not None and "Tensor" in ast.unparse(arg.annotation)
                    if tensor and not shape.search(lines[arg.lineno - 1]):
                        silent.append(f"{p.relative_to(ROOT)}:{arg.lineno} {arg.arg}")
                ret = node.returns
                if ret is not None and "Tensor" in ast.unparse(ret):
                    sig = "\n".join(lines[node.lineno - 1 : ret.end_lineno])
                    if not shape.search(sig.split("->", 1)[-1]):
                        silent.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.name} returns")
    assert not silent, silent


def test_every_link_in_the_docs_leads_somewhere():
    """Relative links and images in README.md and docs/*.md resolve from the file that holds
    them (a link that worked from the repository root once pointed at docs/docs/...)."""
    import re

    broken = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if target.startswith(("http://", "https://", "#", "mailto:")):
                continue
            path = target.split("#", 1)[0]
            if path and not (page.parent / path).exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert not broken, broken


# Folders of the repository a backticked path in the docs may start with.
SCRIPTS = [p for p in (ROOT / "scripts").rglob("*") if p.is_file() and "__pycache__" not in p.parts]
TRACKED_TOPS = ("sagonline/", "bench/", "docs/", "scripts/", "tests/", "conf/", "reports/", ".ci/")


def test_every_backticked_repository_path_in_the_docs_exists():
    """A path in backticks in README.md or docs/*.md that starts with one of the repository's
    folders names a file or folder that is there, a module's attribute (`pkg/mod.attr`), or a
    file one of the project's tools writes (its name in scripts/, bench/ or the Makefile):
    pages that named a renamed test or a moved module were found this way. Paths with
    placeholders (`<name>`, `NAME`, `*`) are patterns, not files."""
    import re

    tools = "\n".join(
        p.read_text()
        for p in [ROOT / "Makefile", *SCRIPTS, *(ROOT / "bench").rglob("*.py")]
        if p.is_file()
    )
    stale = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for token in re.findall(r"`([^`\s]+)`", page.read_text()):
            path = token.rstrip(".,:;").split("::")[0].split(":")[0]
            if not path.startswith(TRACKED_TOPS) or re.search(r"[<>*{}$]|NAME", path):
                continue
            module = path.rsplit(".", 1)[0] + ".py"  # sagonline/fitting/capture.white_backdrop
            if (ROOT / path).exists() or (ROOT / module).exists():
                continue
            if path.rsplit("/", 1)[-1] in tools:  # written by a tool, e.g. reports/gpu_check.md
                continue
            stale.append(f"{page.relative_to(ROOT)}: {token}")
    assert not stale, stale


def cited_reports(text: str) -> list[str]:
    """The `reports/...` files `text` names, in backticks or not; `a.{md,csv}` names both, and
    a name with a placeholder (`reports/NAME.md`, `reports/timing_<model>_cuda.md`,
    `reports/mold_cape.*`) is a pattern and names none."""
    import re

    files = []
    for token in re.findall(r"(?<![\w/])reports/[\w./{},*<>-]*[\w}*>]", text):
        if re.search(r"[<>*]|NAME", token):
            continue
        braces = re.fullmatch(r"(.*)\{([\w,]+)\}(.*)", token)
        if braces:
            head, options, tail = braces.groups()
            files += [f"{head}{option}{tail}" for option in options.split(",")]
        else:
            files.append(token)
    return files


def test_every_report_the_docs_cite_is_there():
    """Each reports/ file README.md, docs/*.md and reports/README.md name is committed, except
    the GPU machine's (`*_cuda.*`, `gpu_check.md`: written there by scripts/gpu_check.sh, and
    absent until a GPU run is committed). Pages moved into a subfolder are found this way."""
    import re

    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "reports/README.md"]
    cited = [(p.relative_to(ROOT), f) for p in pages for f in cited_reports(p.read_text())]
    assert len(cited) > 50
    gpu_machine = re.compile(r"_cuda[._]|gpu_check")
    missing = [
        f"{page}: {f}" for page, f in cited if not (ROOT / f).exists() and not gpu_machine.search(f)
    ]
    assert not missing, missing
    planted = "see reports/no_such.md, reports/timing_cuda.{md,csv} and reports/NAME.md"
    assert cited_reports(planted) == [
        "reports/no_such.md",
        "reports/timing_cuda.md",
        "reports/timing_cuda.csv",
    ]


DOC_PAGES = (ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")))
# Flags of other tools that the docs quote: Hydra's, rerun's, 3DGS's training script's
OTHER_TOOLS_FLAGS = {"--multirun", "--serve-web", "--white_background"}


def backticked(pages=DOC_PAGES) -> list[tuple[str, str]]:
    """(page, text) of every span in backticks of the pages."""
    import re

    return [(p.name, span) for p in pages for span in re.findall(r"`([^`]+)`", p.read_text())]


def unknown_flags(spans) -> list[str]:
    """The `--flags` quoted in `spans` that no command of the project defines (a quoted
    "--flag" in sagonline/, bench/, the Makefile or scripts/) and no other tool owns."""
    import re

    sources = [*ROOT.glob("sagonline/**/*.py"), *ROOT.glob("bench/**/*.py"), ROOT / "Makefile"]
    text = "\n".join(p.read_text() for p in [*sources, *SCRIPTS])
    defined = set(re.findall(r'"(--[a-z][a-z0-9_-]*)"', text)) | OTHER_TOOLS_FLAGS
    return [
        f"{page}: {flag}"
        for page, span in spans
        for flag in re.findall(r"(?<![\w-])(--[a-z][a-z0-9_-]*)", span)
        if flag not in defined
    ]


def unknown_modules(spans) -> list[str]:
    """The `python -m MODULE` commands and dotted `bench.` / `sagonline.` names quoted in
    `spans` that name no module (or no attribute of one)."""
    import importlib
    import importlib.util
    import re

    def exists(name: str) -> bool:
        try:
            if importlib.util.find_spec(name) is not None:
                return True
        except ModuleNotFoundError:
            pass
        module, _, attribute = name.rpartition(".")
        try:
            return bool(module) and hasattr(importlib.import_module(module), attribute)
        except ModuleNotFoundError:
            return False

    names = [
        (page, name)
        for page, span in spans
        for name in re.findall(r"python -m ([a-z_][\w.]*)", span)
        + re.findall(r"^((?:bench|sagonline)\.[\w.]*\w)$", span)
    ]
    return [f"{page}: {name}" for page, name in names if not exists(name)]


def unknown_settings(spans) -> list[str]:
    """The `key.sub=value` settings quoted in `spans` that no composed config has: each key
    looked up in the evaluation's config (the scenes' for fit.*) with every option of its
    group tried (a segmenter's key exists only when that segmenter is picked); keys with
    capitals (`fit.X=...`) are placeholders."""
    import functools
    import re

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from bench.runners.config import register_schemas
    from bench.runners.overrides import GROUPS, group_options

    keys = {
        m.group(1): page
        for page, span in spans
        for token in span.split()
        if (m := re.match(r"^[+~]?([a-z_]+(?:\.[a-z_0-9]+)+)=", token))
        and not token.startswith("hydra.")
    }
    register_schemas()
    absent = object()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):

        @functools.cache
        def composed(schema: str, group: str, option: str | None):
            try:
                return compose(schema, overrides=[f"{group}={option}"] if option else [])
            except Exception:  # an option that does not compose on its own: not this key's
                return None

        def known(key: str) -> bool:
            top = key.split(".")[0]
            schema = "scenes" if top == "fit" else "eval"
            options = [None, *sorted(group_options(top))] if top in GROUPS else [None]
            return any(
                (cfg := composed(schema, top, option)) is not None
                and OmegaConf.select(cfg, key, default=absent) is not absent
                for option in options
            )

        return [f"{page}: {key}" for key, page in sorted(keys.items()) if not known(key)]


@pytest.mark.slow
def test_every_option_command_and_setting_the_docs_quote_exists():
    """What README.md and docs/*.md quote in backticks is what the commands take: each
    `--flag` is defined by one of the project's commands (or is another tool's, named in
    OTHER_TOOLS_FLAGS), each `python -m MODULE` and dotted `bench.`/`sagonline.` name imports,
    and each `key.sub=value` setting is a key of a composed config. A made-up one of each is
    caught, so the check can fail."""
    spans = backticked()
    planted = [("planted", "--no-such-flag"), ("planted", "python -m bench.no_such")]
    planted += [("planted", "consensus.no_such=1"), ("planted", "bench.runners.real.NO_SUCH")]
    assert unknown_flags(spans) == [] and unknown_flags(planted) == ["planted: --no-such-flag"]
    assert unknown_modules(spans) == []
    assert unknown_modules(planted) == [
        "planted: bench.no_such",
        "planted: bench.runners.real.NO_SUCH",
    ]
    assert unknown_settings(spans) == [] and unknown_settings(planted) == [
        "planted: consensus.no_such"
    ]


def test_every_module_the_reports_name_imports_or_is_listed_as_renamed():
    """Each `python -m MODULE` and dotted name a page in reports/ quotes imports today, or is
    an older name in reports/README.md's table, whose name today imports (pages keep the
    commands they were built with; the table says what those are called now)."""
    import re

    readme = ROOT / "reports" / "README.md"
    renamed = dict(re.findall(r"^\| `([\w.]+)` \| `([\w.]+)` \|$", readme.read_text(), re.M))
    assert renamed
    assert unknown_modules([("README.md", new) for new in renamed.values()]) == []
    assert unknown_modules([("README.md", old) for old in renamed]) == [  # no row needed
        f"README.md: {old}" for old in renamed
    ]

    def unlisted(spans) -> list[str]:
        return [m for m in unknown_modules(spans) if m.split(": ", 1)[1] not in renamed]

    pages = sorted((ROOT / "reports").rglob("*.md"))
    assert unlisted(backticked(pages)) == []
    planted = [("planted", "python -m bench.no_such x=1"), ("planted", "python -m bench.real")]
    assert unlisted(planted) == ["planted: bench.no_such"]


def test_the_formatter_runs_everywhere():
    """No `fmt: skip` / `fmt: off` markers: the formatter lays out every line of the library,
    the harness and the tests (a layout it would change is changed, not fenced off)."""
    fenced = [
        f"{p.relative_to(ROOT)}:{i}"
        for p in [
            *PACKAGE.rglob("*.py"),
            *(ROOT / "bench").rglob("*.py"),
            *(ROOT / "tests").rglob("*.py"),
        ]
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if "# fmt: " + "skip" in line or "# fmt: " + "off" in line
    ]
    assert not fenced, fenced


def test_the_own_scene_segmenters_default_is_written_once():
    """`segment.base.DEFAULT_SEGMENTER` is the one place that names the segmenter of a scene
    of one's own; the commands, the viewer and `segment_scene` read it (the registry's own key,
    its declaration in `core/plugins.py` and the old runs' class-name map in
    `pipeline/recorded.py` aside)."""
    allowed = {"segment/base.py", "segment/classical.py", "core/plugins.py", "pipeline/recorded.py"}
    stated = [
        str(p.relative_to(ROOT))
        for p in PACKAGE.rglob("*.py")
        if str(p.relative_to(PACKAGE)) not in allowed
        and ('"classical"' in p.read_text() or "FlowWatershedSegmenter()" in p.read_text())
    ]
    assert not stated, stated


TOP_LEVEL_TESTS = {  # checks of the whole project, not of one room
    "test_layout.py",
    "test_static.py",
    "test_extending.py",
    "test_fuzz_inputs.py",
    "test_gpu_check.py",
}


def test_the_tests_are_sorted_by_the_room_they_test():
    """tests/<room>/ for each room of the package (tests/apps/<app>/ for the front ends) and
    tests/bench/ for the harness; only project-wide checks sit at the top."""
    package = ROOT / "sagonline"
    rooms = {p.name for p in package.iterdir() if (p / "__init__.py").exists()}
    apps = {p.name for p in (package / "apps").iterdir() if p.is_dir() and p.name[0] != "_"}
    misplaced = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        parts = path.relative_to(ROOT / "tests").parts
        if len(parts) == 1:
            ok = parts[0] in TOP_LEVEL_TESTS
        elif parts[0] == "apps":
            ok = len(parts) == 3 and parts[1] in apps
        else:
            ok = parts[0] in rooms | {"bench"}
        if not ok:
            misplaced.append("/".join(parts))
    assert not misplaced, f"tests outside a room's folder: {misplaced}"
