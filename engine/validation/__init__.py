"""Physics validation runs that write reports (``demq validate ...``)."""
