"""The scan on Dask: the stages (workflow), where they run (cluster) and the memory and time predicted
before a run (estimate). The only layer that imports Dask.
"""
