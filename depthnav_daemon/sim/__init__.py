"""Synthetic scenes with exact ground truth: the scene generator (``synthetic``), the bundled
fixtures it writes (``fixtures``) and the paper's box experiment (``paper_experiment``)."""
