"""Many buildings on a Dask cluster: ``facade-batch run BUILDING...`` and ``facade-batch status``.

Each stage of each building is one Dask task that runs that stage through the building's doit tasks
(``doit -s STAGE``: the same up-to-date checks, lock and manifests as a run by hand), chained in pipeline
order within a building; the buildings' chains run side by side on the cluster's workers. The cluster is a
``distributed.LocalCluster`` on this machine by default, a running scheduler, or Slurm through
``dask-jobqueue`` (``cluster``). Each building keeps a record of its stages for ``facade-batch status``
(``record``). Stages that loop over views fan the views out over the same cluster (``fanout``).
"""
