"""After a run: the summary of a recording, the report and its figures, offline tracking experiments."""
