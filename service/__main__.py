"""``python -m service``: the service's one entry point (what ``radarseg serve`` runs). It binds the port at once
and builds the app of :func:`service.main.create_app` on a thread (``service.server.http_server``), so nothing here
imports torch; the same factory serves ``uvicorn --factory service.main:create_app`` and, through
:func:`service.main.build_app`, Ray Serve."""

import sys

from service.server.http_server import main

sys.exit(main())
