"""host.rig: the distributed rig, ``ilcrig run``, ``ilcrig host`` and ``ilcrig robot``.

Owns the host role on the bus (``ilcrig host``):

* :mod:`host.rig.host_role` — the role's entry: builds the canopen network and hands it to the bench;
* :mod:`host.rig.rig_bench` — :class:`~host.rig.rig_bench.RigBench`, the trial loop's bench over CAN,
  composed of the modules below;
* :mod:`host.rig.bring_up` — the nodes from their EDS files, boot-up, heartbeat set-up, NMT start,
  PDO configuration, recovery of a node lost between trials;
* :mod:`host.rig.host_heartbeat` — the host's heartbeat producer (node 127);
* :mod:`host.rig.node_events` — the nodes' heartbeats and EMCY frames as heard;
* :mod:`host.rig.watchdog` — fault detection and declaration (NMT STOP, cancelled SDO requests),
  before, between, during and after trials;
* :mod:`host.rig.fault_classify` — what a fault is: pure functions from an observation to a fault record;
* :mod:`host.rig.trial_runner` — one trial on the plant node, its timing;
* :mod:`host.rig.pdo_stream` — the SYNC producer of the SYNC/RPDO/TPDO lockstep (``--ff-transport pdo``);
* :mod:`host.rig.shutdown` — every live drive torque-free at the end, with the evidence from the bus;
* :mod:`host.rig.channels`, :mod:`host.rig.monitor` — the passive channel monitors (frame and bit
  counts, candump logs, the io channel's trial and tick);
* :mod:`host.rig.bus_accounting` — bus-time figures; :mod:`host.rig.realtime` — trial timing, real-time
  figures, SCHED_FIFO, steal time; :mod:`host.rig.fair_scheduling` — real time without privileges
  (scheduler slice, nice within RLIMIT_NICE, the host in SCHED_BATCH);
  :mod:`host.rig.miss_attribution` — missed ticks beside a kernel scheduler trace;
  :mod:`host.rig.wake_waits` — where the lockstep processes waited for a CPU, from a scheduler trace.

and the launcher (``ilcrig run``), which starts the hub, the plant, the four drives and the host as
processes and always cleans them up:

* :mod:`host.rig.launch_core` — :class:`~host.rig.launch_core.LaunchCore`, what ``ilcrig run`` and
  ``ilcrig robot`` share: the run skeleton, spawning, SCHED_FIFO or the fair-scheduling fallback,
  the idle-poll loops, interrupts, shutdown, the janitor;
* :mod:`host.rig.options` — their typed options (:class:`~host.rig.options.RunOptions`,
  :class:`~host.rig.options.RobotOptions`);
* :mod:`host.rig.launcher` — :func:`~host.rig.launcher.launch_rig`: preflight, the host role, the
  run's outcome, injection;
* :mod:`host.rig.role_commands` — the roles' command lines (``python -P -m host.cli ROLE``, test hooks);
* :mod:`host.rig.processes` — starting (roles, the hub), describing and terminating processes;
* :mod:`host.rig.run_watch` — the run's trial and tick on the io channel, for the launcher;
* :mod:`host.rig.liveness` — the launcher's heartbeat consumer and stop watch: every process watched to the end of the run;
* :mod:`host.rig.supervisor` — the watch loop until the host ends (pidfds: a process's end wakes it);
* :mod:`host.rig.run_outcome` — the run's end: exit code, fault record, drives' evidence, the fault
  line, the run folder as the summary says, a summary on every exit code;
  :mod:`host.rig.role_logs` — the drives' safe-state records in their logs;
  :mod:`host.rig.injection_account` — every ``--inject`` spec accounted for in the summary (a fault,
  tolerated, not injected);
* :mod:`host.rig.janitor` — the run folder settled after a killed launcher (a process of its own);
* :mod:`host.rig.interrupts` — SIGINT / SIGTERM / SIGHUP to the launcher;
* :mod:`host.rig.inject` — kill / stall / EMCY injection; :mod:`host.rig.idle_poll` — the
  SCHED_IDLE loops that keep the CPUs awake in a real-time run; :mod:`host.rig.cpu_latency` — the
  PM QoS CPU latency request that keeps idle CPUs out of halt in a real-time session.

and the robot without the ILC host (``ilcrig robot``, docs/robot.md), on the same processes:

* :mod:`host.rig.robot_launcher` — :func:`~host.rig.robot_launcher.launch_robot`: hub, plant in robot
  mode and drives started, announced, watched until a signal or a fault, cleaned up; the session summary;
* :mod:`host.rig.robot_watch` — what its channel monitors see: boot-ups, SYNCs, EMCYs, the master's
  RPDO set-points and the robot's periods (for the live view).

May import: ``bus`` (incl. ``bus.cia301`` and ``bus.transports``), :mod:`host.nodes`,
:mod:`host.experiment`, :mod:`host.analysis`.  Never ``firmware_model`` or ``plant``: the rig
talks to drives and plant only over the bus.
"""
