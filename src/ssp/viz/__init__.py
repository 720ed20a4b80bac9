"""Pictures of results: estimate-vs-truth overlays and the HTML report."""
