"""HTTP service of the chained-form motion planner (FastAPI; see ``service.main``)."""

__version__ = "0.1.0"
