"""The demq HTTP service (FastAPI) and the ``demq`` command line; built on jobs/ (queue) and engine/."""
