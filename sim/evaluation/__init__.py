"""The Monte Carlo evaluation (pmon eval): trials, methods, metrics, bounds, reports, figures."""
