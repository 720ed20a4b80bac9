"""Pictures of results: estimate-vs-truth overlays, the HTML report and 3D recordings of a run
(:mod:`ssp.viz.record`, what they draw: :mod:`ssp.viz.record_entities`)."""
