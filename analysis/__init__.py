"""Offline analysis of scans and plans: the corpus evaluation, the QA report, image navigation.

Reads scan folders through ``daemon.records.store`` and may use the simulated world (``sim``) for
ground truth; the runtime never imports it.
"""
