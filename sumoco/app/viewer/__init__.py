"""Live browser viewer of a run (``sumoco view``): see ``sumoco.app.viewer.server``."""
