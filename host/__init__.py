"""host: trajectories, ILC laws, trial orchestration, metrics, recording, reports and the
``ilcrig`` command line.  Talks to drives only through :class:`host.links.DriveLink`
(over the bus in the rig); only the composition root :mod:`host.compose` imports the
firmware and plant simulator to run them in-process or as processes."""
