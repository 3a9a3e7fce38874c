"""``surprise-study``: many runs from one file (:mod:`studies.spec`), on local processes or a Dask
cluster (:mod:`studies.executors`, :mod:`studies.runner`), whose workers may be Slurm jobs
(:mod:`studies.slurm`), ending in tables, the paper's statistics and figures
(:mod:`studies.report`; a changing arena's recovery across seeds: :mod:`studies.recovery`). See
docs/studies.md."""
