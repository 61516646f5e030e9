"""
Make every gallery figure
=========================

Run each ``gallery/fig*.py`` script's ``main(out_dir, size=...)`` in turn,
off screen, and list the pictures written with their sizes and times.

    python gallery/make_all.py --out gallery_out [--size W H]
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def figure_scripts(folder: Path = HERE) -> list[Path]:
    """The figure scripts of the gallery, in name order."""
    return sorted(folder.glob("fig*.py"))


def load(script: Path):
    """Import a gallery script as a module (without running its ``__main__``)."""
    spec = importlib.util.spec_from_file_location(f"gallery_{script.stem}", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def main(out_dir, size=None, scripts=None) -> list[dict]:
    """Run the figure scripts; return one record per script (name, seconds, pngs)."""
    from gatv import render

    render.configure_offscreen()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    records = []
    for script in scripts if scripts is not None else figure_scripts():
        print(f"== {script.name}", flush=True)
        t0 = time.perf_counter()
        module = load(script)
        result = module.main(out_dir, size=tuple(size)) if size is not None else module.main(out_dir)
        seconds = time.perf_counter() - t0
        pngs = [Path(p) for p in (result or {}).get("pngs", [])]
        records.append({"script": script.name, "seconds": seconds, "pngs": pngs})
    print("\nfigure                          seconds  picture")
    total = 0.0
    for r in records:
        total += r["seconds"]
        shown = ", ".join(f"{p.name} {w}x{h} ({p.stat().st_size // 1024} KiB)"
                          for p in r["pngs"] for w, h in [_png_size(p)])
        print(f"{r['script']:<32}{r['seconds']:7.1f}  {shown}")
    print(f"{'total':<32}{total:7.1f}")
    return records


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="Render every gallery figure off screen.")
    parser.add_argument("--out", type=Path, default=Path("gallery_out"), help="output folder")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="picture size for every figure")
    args = parser.parse_args()
    main(args.out, size=args.size)
    sys.exit(0)
