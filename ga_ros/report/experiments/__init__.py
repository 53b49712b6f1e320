"""The paper's experiments, each returning JSON-ready numbers plus the arrays its plots need.

One module per experiment (or family of experiments):

* :mod:`.table1`: Table I and Fig. 5 (Sec. V-A): F2F vs GA mean position error of the four
  synthetic trajectories at each noise level, ``runs`` Monte-Carlo runs each.
* :mod:`.future_tracks`: Fig. 2/3 (Sec. IV): how much each new track moves the track-1
  positions.
* :mod:`.survey`: Fig. 7/8 and the window-versus-batch gap (Sec. IV, V-B): a survey aligned
  online track by track with :class:`~ga_ros.core.window.TrackWindowAligner`, against the full
  batch solution (with its quality control) and F2F, with per-track update times
  (:func:`~.survey.survey_window`); the aerial survey with synthetic noise
  (:func:`~.survey.aerial_window`) and experiment 2 both go through it.
* :mod:`.policies`: the freeze policies on several noise draws of the aerial survey, with the
  paired difference of each policy's gap to batch against weighted (mean, sd, t interval).
* :mod:`.memory`: peak memory of one track update for two survey sizes.
* :mod:`.experiment2`: experiment 2 (Sec. V-B) from rendered stereo and our VO, with the VO's
  NEES and Fig. 12's registration of neighbouring swaths.
* :mod:`.wrong_connections`: the wrong-connection table (:mod:`ga_ros.bench.outliers`).

Every random draw comes from :func:`.seeds.run_rng` so any single number can be recomputed
alone.
"""
