"""`magcomp fleet`: every log of every vehicle (issue 28).

discover (logs under paths, the vehicle mapping file) -> engine (content hashes, what is done, Dask) ->
analyse (one log: identity + the two-pass replay -> rows, in a worker) -> store (one Parquet part per log,
atomically) -> vehicles (theta per vehicle over time, changes via magcomp.core.changes, the inspect list)
-> report (one static HTML page). docs/fleet.md describes it for users.
"""
