"""Benchmarks: ``testbed bench`` (:mod:`studies.bench.suite`) and one script per workload.

Each prints its figures beside the goal and a reference measured in the same run; none is a
timed unit test.
"""
