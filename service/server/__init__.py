"""The process that serves: uvicorn bound at once with the settings' HTTP limits (``http_server``), answering through
an app that says "starting" until the service's app is built and its models load (``starting_app``)."""
