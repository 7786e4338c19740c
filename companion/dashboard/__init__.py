"""`companion dashboard`: the read-only live telemetry page for a ground laptop.

:mod:`~companion.dashboard.hub` keeps the last sample of every zenoh key and fans samples out
to the browsers; :mod:`~companion.dashboard.web` serves the page (``static/``) and pushes
updates over server-sent events; :mod:`~companion.dashboard.app` wires both to a zenoh
session. :mod:`~companion.dashboard.headless` drives Debian's headless Chromium for the tests
and :mod:`~companion.dashboard.bench` measures publish-to-browser latency. Page and
architecture: docs/dashboard.md.
"""
