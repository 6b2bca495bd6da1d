"""What each call of the GPU plan carries to a GPU machine, against the 64 MiB it may carry.

    python scripts/carry_sizes.py --call .gpu-bundle [--call "PATH PATH ..."]

A call carries the checkout's tracked files and the ignored paths it names (docs/performance.md,
"One command on a GPU machine"). For each --call this prints the tracked tree, each path and
the total, and exits 1 when a total is over the limit, so that `make gpu-bundle` fails here
rather than the call there. A path that is not here (weights never fetched) is said and skipped.
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

LIMIT_BYTES = 64 * 2**20
ROOT = Path(__file__).resolve().parents[1]


def size_of(path: Path) -> int:
    """Bytes in a file, or under a folder counted as `du -sb` counts them (its files and its
    folders' own entries): an upper bound on what travels."""
    if path.is_file():
        return path.stat().st_size
    return path.stat().st_size + sum(p.lstat().st_size for p in path.rglob("*"))


def tracked_bytes(root: Path) -> int:
    """Bytes in the checkout's tracked files (as they are on disk)."""
    names = subprocess.run(
        ["git", "ls-files", "-z"], cwd=root, capture_output=True, check=True
    ).stdout.split(b"\0")
    return sum(size_of(root / n.decode()) for n in names if n and (root / n.decode()).exists())


def check_calls(calls: list[list[str]], root: Path, limit: int = LIMIT_BYTES) -> list[str]:
    """Each call's lines (tracked tree, its paths, total); a call over `limit` as a line that
    starts with 'over'. A path that is not here is said and left out."""
    tree = tracked_bytes(root)
    lines = []
    for number, paths in enumerate(calls, 1):
        total = tree
        lines.append(f"call {number}: tracked tree {tree / 1e6:.1f} MB")
        for name in paths:
            path = root / name
            if not path.exists():
                lines.append(
                    f"  {name}: not here (`make gpu-bundle`, `make weights`), so not carried"
                )
                continue
            total += size_of(path)
            lines.append(f"  {name}: {size_of(path) / 1e6:.1f} MB")
        room = (limit - total) / 1e6
        verdict = f"{room:.1f} MB to spare" if room >= 0 else f"{-room:.1f} MB too many"
        lines.append(f"  total {total / 1e6:.1f} MB of {limit / 1e6:.1f} MB: {verdict}")
        if total > limit:
            lines.append(
                f"over: call {number} carries {total / 1e6:.1f} MB, over {limit / 1e6:.1f} MB"
            )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--call", action="append", required=True, help="the paths one call carries")
    ap.add_argument("--root", type=Path, default=ROOT, help="the checkout (default: this one)")
    ap.add_argument("--limit", type=int, default=LIMIT_BYTES, help="bytes a call may carry")
    args = ap.parse_args()
    calls = [c.split() for c in args.call if c.split()]  # "": no such call
    lines = check_calls(calls, args.root, args.limit)
    print("\n".join(lines))
    if any(line.startswith("over") for line in lines):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
