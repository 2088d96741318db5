"""Evaluation: the field's metrics, per-scene evaluation against ground truth, the ``sparseart bench``
grid with the ICP peer beside sparseart, plots and the stability report."""
