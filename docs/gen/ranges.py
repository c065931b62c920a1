"""Write reference/input-ranges.md from ``inject.validate.RANGES`` at build time, so the page
always shows the ranges the code checks."""
import sys
from pathlib import Path

import mkdocs_gen_files

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import importable  # noqa: E402

importable()
from inject.validate import ranges_markdown  # noqa: E402

INTRO = """\
# Input ranges

Every number a scene file or a command-line option sets is checked against one table,
`inject.validate.RANGES`, before any work starts. This page is generated from that table
when the documentation is built, so it is the table the code uses.

* **Accepted**: outside this range the value is refused: the command stops with exit
  status 2 and one line naming the value, the range and the reason (the *why* column).
* **Warned**: inside the accepted range but outside the plausible one, the value is used
  and a one-line warning goes to stderr (`inject simulate: warning: ...`).
* **Options**: the command-line options checked against the same row (a scene key
  without options is set only in scene files).

Values that would hang, crash or fill the memory are refused (`cosmic_rays=1e12`,
`exptime=1e30`, `detector.nx=100000`); values that are physically absurd but harmless to
compute are warned about (`--height 1e9`, beyond the Moon) or, where no satellite could
have them, refused (`--mag -50`, brighter than the Sun; `--height 50`, below any orbit).
A polyline vertex's keys are checked as the satellite's own.

Two checks are not single numbers:

* **Charge**: the brightest pixel's expected charge (sky, dark current, the brightest
  star and each satellite's charge per pixel of track, an upper bound computed without
  building a profile) must stay within `charge_per_px` (last row).
* **Memory**: `inject simulate` needs about 64 bytes per pixel (a measured peak of 44-46
  with every output written); a scene that needs more than the memory available
  (`MemAvailable` in `/proc/meminfo`) is refused before any work, with both numbers.

A key given twice in one YAML mapping is refused with both line numbers; a
`key.path=value` override given twice on the command line follows the usual rule: the
last one wins.

"""


with mkdocs_gen_files.open("reference/input-ranges.md", "w") as f:
    f.write(INTRO + ranges_markdown() + "\n")
