"""The application around the scene-parsing core: ``ssp run`` and its relatives, with files in
and files out. Modules (each imported on its own; this package imports none of them):

* :mod:`ssp.pipeline.sources`: the :class:`~ssp.pipeline.sources.FrameSource` protocol every run
  input implements, and :class:`~ssp.pipeline.sources.InputFrame`, one frame of it;
* :mod:`ssp.pipeline.folder`, :mod:`ssp.pipeline.bop`, :mod:`ssp.pipeline.bag`: the sources of a
  folder of clouds, a BOP scene and a ROS bag / MCAP file (and the bag's results bag);
* :mod:`ssp.pipeline.inputs`: which source reads an input path, and the files it is read from;
* :mod:`ssp.pipeline.manifest`: the output folder of a run: ``run.json``, ``state.json``, the
  checks of a new run's folder and of a resume;
* :mod:`ssp.pipeline.summary`: :class:`~ssp.pipeline.summary.RunSummary` (``summary.json``);
* :mod:`ssp.pipeline.run`: :func:`~ssp.pipeline.run.run`, the frame loop;
* :mod:`ssp.pipeline.batch`: many inputs, one run each, in parallel;
* :mod:`ssp.pipeline.executor`: mapping independent work items serially, on processes or Ray;
* :mod:`ssp.pipeline.refine`: ``ssp refine``, ``ssp estimate``, ``ssp evaluate`` on BOP datasets;
* :mod:`ssp.pipeline.models`: what ``ssp models`` reports about a model.
"""
