"""Live browser viewer of a run (``sumoco view``): see ``sumoco.viewing.viewer.server``."""
