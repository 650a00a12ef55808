"""Robustness sweeps: one scenario run for thousands of perturbed plants and gains, on Dask.

``spec`` reads the sweep's TOML, ``sampling`` makes each sample's inputs and scenario file
(and the data a worker reads it as), ``execute`` runs the samples on Dask workers, ``results``
keeps the rows as Parquet part files (resumable), ``report`` draws the robustness map. The
per-sample measurement (a run's summary as cochlea-run writes it) is the caller's
``evaluate``: see cochlea/apps/cochlea_sweep.py.
"""
