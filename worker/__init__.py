"""RQ workers for the pbrsr job service: ``pbrsr worker`` runs :mod:`worker.runner`, which
executes :func:`worker.tasks.run_job` for each job the API enqueues."""
