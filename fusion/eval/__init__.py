"""Evaluation of the method, outside it: metrics, the one gauge alignment, the bench, ablations,
throughput, the classical baseline and the synthetic fleet. The method never imports this package."""
