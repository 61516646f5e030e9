"""Sphinx configuration of the gatv documentation (``make docs``).

The API reference comes from the numpydoc docstrings (autodoc + numpydoc);
the gallery from ``gallery/fig*.py`` through sphinx-gallery, rendered off
screen (switched on here, in one place).  Each figure script runs as
``python figNN.py --out <build>/gallery_pngs/figNN`` and the pictures it
writes there are shown under its last section (:class:`FigurePngs`).

``-D plot_gallery=0`` builds the pages without running the scripts.

Modules get their API page from ``docs/api/*.rst`` (grouped by hand); a
public module no page names yet is listed on ``api/more.rst``, written at
every build (:func:`write_more_page`), so none is left out.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
import re
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

# off-screen rendering for every gallery script, before PyVista is imported
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
import pyvista

pyvista.OFF_SCREEN = True
from gatv import render

render.configure_offscreen()

import gatv

project = "gatv"
author = "the gatv developers"
copyright = "2026, the gatv developers"
release = gatv.__version__
version = ".".join(release.split(".")[:2])

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
    "sphinx_gallery.gen_gallery",
    "myst_parser",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "auto_examples/*.ipynb", "auto_examples/*.py", "auto_examples/*.zip",
                    "auto_examples/*.json", "auto_examples/*.md5", "sg_execution_times.rst"]
suppress_warnings = ["myst.header", "myst.xref_missing", "config.cache"]

autodoc_default_options = {"member-order": "bysource"}
autodoc_typehints = "none"  # numpydoc's shaped types say more
numpydoc_show_class_members = False
numpydoc_validation_checks: set = set()
numpydoc_xref_param_type = False


html_theme = "pydata_sphinx_theme"
html_title = f"gatv {release}"
html_theme_options = {"show_toc_level": 2, "navigation_with_keys": False}

GALLERY_OUT = HERE / "_build" / "gallery_pngs"


def figure_argv(gallery_conf, script_vars) -> list[str]:
    """``sys.argv[1:]`` of a figure script under sphinx-gallery: its own output folder."""
    return ["--out", str(GALLERY_OUT / Path(script_vars["src_file"]).stem)]


class FigurePngs:
    """sphinx-gallery scraper: the PNG files a figure script wrote into its ``--out`` folder.

    The scripts save and close their plotters themselves (``render.save``),
    so PyVista's own scraper finds no open plotter; the pictures are picked
    up from the folder instead, each once, after the block that wrote it.
    """

    def __init__(self):
        self.seen: set[str] = set()

    def __call__(self, block, block_vars, gallery_conf):
        from sphinx_gallery.scrapers import figure_rst

        folder = GALLERY_OUT / Path(block_vars["src_file"]).stem
        new = [p for p in sorted(folder.glob("*.png")) if str(p) not in self.seen] if folder.is_dir() else []
        written = []
        for png, dest in zip(new, block_vars["image_path_iterator"]):
            shutil.copyfile(png, dest)
            self.seen.add(str(png))
            written.append(dest)
        return figure_rst(written, gallery_conf["src_dir"])

    def __repr__(self) -> str:  # a stable config value for Sphinx's environment pickle
        return "FigurePngs()"


sphinx_gallery_conf = {
    "examples_dirs": [str(ROOT / "gallery")],
    "gallery_dirs": ["auto_examples"],
    "filename_pattern": r"/fig\d+",
    "ignore_pattern": r"make_all\.py|__init__\.py",
    "image_scrapers": (FigurePngs(),),
    "reset_argv": figure_argv,
    "within_subsection_order": "FileNameSortKey",
    "download_all_examples": False,
    "remove_config_comments": True,
    "capture_repr": (),
    "abort_on_example_error": False,
    "only_warn_on_example_error": True,
}


# ------------------------------------------------------------ API coverage
PACKAGES = ("gatv", "catadioptric")
MORE = HERE / "api" / "more.rst"


def public_modules() -> list[str]:
    """Every module of gatv and catadioptric whose dotted name has no ``_`` part."""
    names = []
    for package in PACKAGES:
        pkg = importlib.import_module(package)
        names.append(package)
        names += [info.name for info in pkgutil.walk_packages(pkg.__path__, f"{package}.")
                  if not any(part.startswith("_") for part in info.name.split("."))]
    return names


def documented_modules() -> set[str]:
    """Modules named by an ``automodule`` directive of the hand-written API pages."""
    found = set()
    for page in (HERE / "api").glob("*.rst"):
        if page != MORE:
            found |= set(re.findall(r"^\.\. automodule:: (\S+)", page.read_text(), flags=re.MULTILINE))
    return found


def more_page() -> str:
    """The text of ``api/more.rst``: the public modules no hand-written page documents."""
    rest = [m for m in public_modules() if m not in documented_modules()]
    lines = ["More modules", "============", ""]
    if not rest:
        lines.append("Every public module is on one of the pages above.")
    for name in rest:
        lines += [f"``{name}``", "-" * (len(name) + 4), "", f".. automodule:: {name}", "   :members:",
                  "   :show-inheritance:", ""]
    return "\n".join(lines) + "\n"


def write_more_page(app=None) -> None:
    text = more_page()
    if not MORE.exists() or MORE.read_text() != text:
        MORE.write_text(text)


def setup(app):
    app.connect("builder-inited", write_more_page)
    return {"parallel_read_safe": True}
