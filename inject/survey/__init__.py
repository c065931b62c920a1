"""A survey night: which visits a satellite constellation streaks, and the pixels its masks cost.

- :mod:`~inject.survey.visits`: the visits of an opsim database (SQLite, table
  ``observations``) or a CSV with its columns.
- :mod:`~inject.survey.nights`: the same read night by night (the local date at the site,
  noon to noon), never whole; the Sun's altitude at each visit.
- :mod:`~inject.survey.constellation`: the constellation file (the satellites' model, Walker
  shells and TLE files).
- :mod:`~inject.survey.prefilter`: the constellation propagated once over the night, and per
  visit the satellites that may cross the field sunlit.
- :mod:`~inject.survey.plan`: per visit, the sunlit crossings of the science CCDs, each with its
  length, magnitude, FWHM, peak surface brightness, mask width and the pixels its mask takes.
- :mod:`~inject.survey.fixed_mask`: ``--mask-width``, a band of one width along every
  streak counted beside the plan's mask.
- :mod:`~inject.survey.rubin_rule`: ``--rule rubin_sim``, the visits counted as rubin_sim's
  ``check_pointings`` counts them (the literature's rule), with a fixed band in the circle.
- :mod:`~inject.survey.render`: ``--render``: the streaked CCDs of each visit rendered as a
  focal-plane scene of the visit on the focal plane's runner.
- :mod:`~inject.survey.compare`: what the masker measures on a rendered CCD, matched to the
  planned tracks, and the ``measured_*`` columns of ``streaks.csv``.
- :mod:`~inject.survey.stream`: each night's tables as Parquet files and a manifest as the
  night finishes (a stopped run goes on where it stopped), and the run's summary made from
  them.
- :mod:`~inject.survey.outputs`: ``streaks.csv``, ``visits.csv``, ``summary.json`` and the
  plots, written together (:func:`inject.io.atomic.output_group`).

The command line is :mod:`inject.cli.survey` (``inject survey``).
"""
