"""``ocpar serve``: the HTTP job API (FastAPI on uvicorn) and its page.

* :mod:`~ocpar.service.web.app`: the endpoints (:func:`~ocpar.service.web.app.create_app`);
* :mod:`~ocpar.service.web.store`: the SQLite tables of tokens and jobs, the job directories;
* :mod:`~ocpar.service.web.tokens`: bearer tokens, stored as SHA-256 hashes;
* :mod:`~ocpar.service.web.runner`: the supervisor that starts, watches and recovers jobs;
* :mod:`~ocpar.service.web.events`: progress lines → figures for the event stream;
* :mod:`~ocpar.service.web.serve`: the ``ocpar serve`` command;
* ``static/``: the page served at ``/``.
"""
