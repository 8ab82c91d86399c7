"""ocpar as a service: detached runs (jobs) on a Dask cluster, their state and results.

* :mod:`ocpar.service.jobs`: the job directories on the scheduler's host and the functions
  the scheduler runs for clients (create, start, list, status, files, cancel);
* :mod:`ocpar.service.coordinator`: the detached process that runs one job's coordinator;
* :mod:`ocpar.service.client`: the Python API behind ``ocpar submit|jobs|status|result|cancel``;
* :mod:`ocpar.service.web`: the HTTP job API ``ocpar serve`` (its jobs in the same directories,
  run by the same command lines: :func:`ocpar.service.jobs.run_command`).
"""
