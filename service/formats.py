"""Figure formats and kinds (light: the routers use them without importing matplotlib)."""

#: Output format -> media type.
FORMATS: dict[str, str] = {"png": "image/png", "svg": "image/svg+xml"}
#: Figure kinds accepted by :func:`service.figures.render`.
KINDS = ("joint_angles", "chained_state", "robustness", "sweep", "pareto")
