"""The JSON API, one module per resource; service/app.py includes :data:`ROUTERS` (the HTML pages
are service/web.py)."""

from service.routes import analyses, batches, devices, health, keys, limits, recordings, runs, stations

#: Every API router, in the order OpenAPI lists them.
ROUTERS = [health.router, stations.router, runs.router, batches.router, analyses.router, devices.router,
           limits.router, recordings.router, keys.router]
