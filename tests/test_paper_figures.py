"""scripts/paper_figures.py writes the paper's four figures and the 350/550 km peak ratio."""
import importlib.util
import re
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "paper_figures.py"
FIGURES = ("fig1_range.png", "fig2_teff.png", "fig3_profiles.png", "fig4_cross_sections.png")


def load_script():
    spec = importlib.util.spec_from_file_location("paper_figures", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_paper_figures(tmp_path, capsys):
    out = tmp_path / "figures"  # does not exist yet: main must create it
    load_script().main(["--out", str(out)])
    printed = capsys.readouterr().out
    for name in FIGURES:
        path = out / name
        assert path.is_file(), name
        assert path.stat().st_size > 10_000, name
        assert f"wrote {path}" in printed
    match = re.search(r"peak surface brightness 350/550 km: (\S+)", printed)
    assert match, printed
    assert float(match.group(1)) == pytest.approx(1.04, abs=0.01)
    assert len(re.findall(r"FWHM at \d+ km: \d+\.\d+ arcsec", printed)) == 2
