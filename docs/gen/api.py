"""Write the API reference pages (reference/api/*.md) at build time: one page per part of the
package, with a mkdocstrings block for each of its modules that exists in this checkout.

Each module is listed by its name in the package's folder layout first and by its earlier
flat name after it, so the pages follow the code whichever layout it has.
"""
import sys
import tomllib
from pathlib import Path

import mkdocs_gen_files

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, importable, module_exists  # noqa: E402

#: (page, title, introduction, [(module, earlier name or None), ...])
PAGES = [
    ("physics", "Physics",
     "From an orbit, a line of sight and a satellite to the streak's profile and charge.",
     ["inject.instrument", "inject.geometry", "inject.satellite",
      "inject.photometry", "inject.profile", "inject.optics", "inject.streak"]),
    ("rendering", "Rendering",
     "Tracks on the pixel grid and the renderer that sweeps a profile along them, with the "
     "brute-force reference and the baselines it is measured against.",
     ["inject.trajectory", "inject.render", "inject.reference",
      "inject.baselines"]),
    ("scenes", "CCD scenes and add-streak",
     "Scene files, star fields, one simulated CCD, and injection into an existing image.",
     ["inject.config", "inject.stars", "inject.skytiles",
      "inject.scene", "inject.addstreak"]),
    ("camera", "Camera",
     "LSSTCam: the focal-plane layout and distortion, the two sensor types, and every WCS "
     "builder.",
     ["inject.camera.layout", "inject.camera.detector",
      "inject.camera.wcs"]),
    ("orbits", "Orbits",
     "Real passes from TLEs or circular orbits, their conversion into tracks, and the "
     "optional lumos-sat brightness.",
     ["inject.orbits.passes", "inject.orbits.tracks",
      "inject.orbits.lumos"]),
    ("exposure", "Whole exposure",
     "Focal-plane scenes, the plan of which CCD gets which streak, one CCD of the exposure, "
     "the runner (process pool or Dask), the job's CPUs and memory, and the mosaic.",
     ["inject.exposure.scene", "inject.exposure.plan",
      "inject.exposure.ccd", "inject.exposure.runner",
      "inject.exposure.sizing", "inject.exposure.mosaic"]),
    ("io", "Files",
     "FITS, OpenEXR and quicklook writers, the reader of users' files, and atomic output.",
     ["inject.io", "inject.io.atomic", "inject.io.fits",
      "inject.io.exr", "inject.io.quicklook", "inject.io.reader"]),
    ("masking", "Masking",
     "Detection, measurement and masking of streaks, and the scoring of maskers against "
     "injected truth.",
     ["inject.masking", "inject.masking.run", "inject.masking.detect",
      "inject.masking.measure", "inject.masking.mask",
      "inject.masking.geometry", "inject.masking.evaluate",
      "inject.masking.external", "inject.masking.baseline",
      "inject.masking.synthetic"]),
    ("survey", "Survey night",
     "A night of visits against a constellation: the visits, the satellites, the plan of "
     "which visit each satellite streaks and what its masks cost, and the outputs.",
     ["inject.survey", "inject.survey.visits", "inject.survey.constellation",
      "inject.survey.prefilter", "inject.survey.plan", "inject.survey.render",
      "inject.survey.compare",
      "inject.survey.outputs"]),
    ("cli", "Command line",
     "The parser and entry point of the `inject` command, and one module per command; every "
     "command's options are in [Command line](../cli.md).",
     ["inject.cli.main", "inject.cli.options", "inject.cli.logs", "inject.cli.profile",
      "inject.cli.simulate",
      "inject.cli.add_streak", "inject.cli.focalplane", "inject.cli.satellite_pass",
      "inject.cli.mask", "inject.cli.evaluate", "inject.cli.survey"]),
    ("foundations", "Foundations",
     "Errors, the input ranges, the scene-schema helpers every parser uses, clean stops on "
     "signals, progress reports, and the mask planes: the modules every other part builds on.",
     ["inject.errors", "inject.validate", "inject.schema",
      "inject.signals", "inject.progress", "inject.maskplanes", "inject.truth"]),
]


def layers():
    """The layer contract of ``pyproject.toml`` (import-linter), top to bottom, or None."""
    try:
        config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError):
        return None
    for contract in config.get("tool", {}).get("importlinter", {}).get("contracts", []):
        if contract.get("type") == "layers":
            return [layer.replace("inject.", "") for layer in contract["layers"]]
    return None


#: Per-module options (the command line's module holds one private helper per command).
OPTIONS = {"inject.cli.main": "members: [build_parser, main]"}

for page, title, intro, modules in PAGES:
    lines = [f"# {title}", "", intro, ""]
    found = [m for m in modules if module_exists(m)]
    for module in found:
        lines.append(f"::: {module}")
        if module in OPTIONS:
            lines += ["    options:", f"      {OPTIONS[module]}"]
        lines.append("")
    if not found:
        lines.append("(No module of this part exists in this checkout.)")
    with mkdocs_gen_files.open(f"reference/api/{page}.md", "w") as f:
        f.write("\n".join(lines))

# The index: the parts, and the one direction imports run in.
index = ["# API", "",
         "The package is a flat core for one CCD (physics, rendering, scenes) with wings in "
         "folders: the camera, orbits, the whole exposure, masking, files and the command "
         "line. Each page documents the modules of one part.", "",
         "| part | modules |", "|---|---|"]
for page, title, _, modules in PAGES:
    names = ", ".join(f"`{m}`" for m in modules if module_exists(m))
    index.append(f"| [{title}]({page}.md) | {names} |")

# The names ``inject`` itself exports (imported on first use), with the page of each.
importable()
import inject  # noqa: E402

exported = getattr(inject, "_API", {})  # public name -> defining module
if exported:
    page_of = {m: page for page, _, _, modules in PAGES for pair in modules for m in pair if m}
    index += ["", "## `import inject`", "",
              "These names are importable from the package itself (`inject.simulate`, "
              "`inject.StreakModel`, ...); each module is imported only when one of its names "
              "is first used.", "", "| name | defined in |", "|---|---|"]
    for name, module in exported.items():
        page = page_of.get(module)
        where = f"[`{module}`]({page}.md)" if page else f"`{module}`"
        index.append(f"| `{name}` | {where} |")

order = layers()
if order:
    index += ["", "## Layers", "",
              "Imports run one way, from the command line down to the errors: a module may "
              "import only from the layers below its own, and the parts of one layer separated "
              "by `|` do not import each other. The layers, top to bottom (from "
              "`pyproject.toml`, where `make lint` checks them with import-linter):", "",
              "```text", *order, "```"]
with mkdocs_gen_files.open("reference/api/index.md", "w") as f:
    f.write("\n".join(index) + "\n")
