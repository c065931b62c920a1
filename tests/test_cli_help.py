"""The command line as a newcomer meets it: help without markup and with defaults, one
spelling of the output option everywhere, the truth visible on the quicklook."""
import re

import numpy as np
import pytest

from inject.cli.main import build_parser, main


def _help(capsys, *command):
    with pytest.raises(SystemExit) as exit_info:
        main([*command, "--help"])
    assert exit_info.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", ["profile", "simulate", "add-streak", "mask", "evaluate"])
def test_help_has_no_markup(capsys, command):
    text = _help(capsys, command)
    assert not re.search(r":(func|class|mod|data|meth):|``", text), text


def test_profile_help_shows_defaults(capsys):
    text = " ".join(_help(capsys, "profile").split())
    for option, default in (("--zenith DEG", "0.0"), ("--phi DEG", "90.0"),
                            ("--seeing ARCSEC", "0.67"), ("--band BAND", "g"),
                            ("--mag MAG", "5.0"), ("--ref-range KM", "550.0"),
                            ("--pixel-scale ARCSEC", "0.2"), ("--length M", "7.25"),
                            ("--width M", "2.65"), ("--radius M", "1.0")):
        entry = re.search(re.escape(option) + r" (.*?)\(default: ([^)]*)\)", text)
        assert entry and entry.group(2) == default, option
    assert "(default: None)" not in text and "(default: False)" not in text


@pytest.mark.parametrize("command,dest", [
    (["simulate", "s.yaml"], "output"), (["add-streak", "in.fits", "--height", "550"], "output"),
    (["mask", "in.fits"], "out"), (["evaluate"], "out"), (["focalplane", "s.yaml"], "output")])
@pytest.mark.parametrize("spelling", ["-o", "--output", "--out"])
def test_every_command_takes_every_output_spelling(command, dest, spelling):
    args = build_parser().parse_args([*command, spelling, "x"])
    assert getattr(args, dest) == "x"


def test_quicklook_truth_is_visible_beside_a_saturated_streak():
    """A saturated streak renders white; the truth marks run either side of the track (its
    centre line stays uncovered) in a colour that is neither white nor grey, outlined in black,
    so they show on the white streak."""
    from inject import SceneResult
    from inject.io.quicklook import TRUTH_OFFSET_PT, quicklook_figure
    ny = nx = 200
    image = np.full((ny, nx), 100.0)
    image[95:106, :] = 1e6  # a saturated horizontal streak along y = 100
    truth = [{"x0": -0.5, "y0": 100.0, "x1": nx - 0.5, "y1": 100.0, "flags": 4}]
    result = SceneResult(image=image, mask=np.zeros((ny, nx), np.int32),
                         variance=np.ones((ny, nx)), streak_model=np.zeros((ny, nx)),
                         truth=truth, sky_level=100.0, noise_sigma=1.0)
    fig, ax = quicklook_figure(result)
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(int)
    height = rgba.shape[0]
    x_pix, y_mid = ax.transData.transform((nx / 2, 100.0))
    col = int(round(x_pix))
    column = rgba[:, col - 20:col + 20]  # a band across the streak, away from the label

    def row(y):
        return height - 1 - int(round(ax.transData.transform((nx / 2, y))[1]))

    coloured = (column.max(axis=2) - column.min(axis=2)) > 80  # not grey: the truth colour
    centre = slice(row(100.6), row(99.4) + 1)
    assert (column[centre] > 250).all()  # the track itself: white, not covered
    offset_px = TRUTH_OFFSET_PT * fig.dpi / 72
    above, below = int(round(height - 1 - y_mid - offset_px)), int(round(height - 1 - y_mid
                                                                         + offset_px))
    assert coloured[above - 2:above + 3].any() and coloured[below - 2:below + 3].any()
    dark = column.max(axis=2) < 60  # the black outline: contrast with the white streak
    assert dark[above - 4:above + 5].any() and dark[below - 4:below + 5].any()


COMMANDS = ["profile", "simulate", "add-streak", "mask", "evaluate", "focalplane", "pass",
            "survey"]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_has_help_and_one_default_style(capsys, command):
    """Defaults read '(default: X)' once; a bare '(2)' or '(default 3GiB)' is another style,
    and a default written by hand beside argparse's is said twice."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices[command]
    for action in sub._actions:
        assert action.help, f"inject {command} {action.option_strings or action.dest}"
    text = " ".join(_help(capsys, command).split())
    assert not re.search(r"\(default [^:]", text), text
    for entry in re.split(r" (?=-{1,2}[a-z])", text):
        assert entry.count("(default") <= 1, entry
        assert not re.search(r"\(\d+(\.\d+)?\)", entry), entry


def test_retries_and_njobs_say_what_they_are(capsys):
    text = " ".join(_help(capsys, "focalplane").split())
    assert "--retries N resubmissions of a failed CCD (default: 2)" in text
    assert re.search(r"--njobs N with --job: the number of slices", text)


@pytest.mark.parametrize("command", COMMANDS)
def test_help_places_the_samples_in_the_repository(capsys, command):
    """An installed wheel has no sample_fields/: help that names it says where it is."""
    text = " ".join(_help(capsys, command).split())
    for match in re.finditer(r"sample_fields/", text):
        assert text[max(0, match.start() - 30):match.start()].endswith("the repository's "), \
            text[match.start() - 60:match.end()]
