"""Synthetic scenes with exact ground truth: the scene generator (``synthetic``), the truth per
bearing computed from the scene's geometry (``truth``), drives along a trajectory with odometry
(``drive``), the bundled fixtures it writes (``fixtures``) and the paper's box experiment
(``paper_experiment``)."""
