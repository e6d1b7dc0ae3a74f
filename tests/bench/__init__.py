"""Benchmarks: ``./dev bench [NAME ...]`` runs every module here that defines ``run()``.

Each ``run()`` prints its measured numbers and the goal beside them. They are not tests:
they measure speed and memory on this machine and assert nothing.
"""
