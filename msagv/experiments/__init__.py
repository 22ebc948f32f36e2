"""The study: scenarios, experiment runs, reports, tables and figures.

* :mod:`experiments.scenario` -- :class:`Scenario`, one description of a closed-loop run and
  the one place that assembles its plant, controller and reference;
* :mod:`experiments.runs` -- cached, parallel closed-loop runs keyed by their configuration;
* :mod:`experiments.cases` -- the paper's Cases 1-3 (with the study's references), the
  Pareto fronts and the ridge experiment;
* :mod:`experiments.study` -- the study's design (scenarios, runs, wear floors);
  :mod:`experiments.study_analysis` -- its analysis (fronts at equal error, confidence
  intervals, tables and figures);
* :mod:`experiments.tables`, :mod:`experiments.paper` -- the paper's table layout, its
  transcribed numbers, figures of the experiments;
* :mod:`experiments.plots` -- the figure of one run; :mod:`experiments.recorded` -- metrics
  from a Zenoh recording (``msagv report``, ``msagv demo``).

Imports plant, controller, bridge and fmu_build; nothing below imports this package.
"""
