"""firmware_model: the servo drive's firmware.

Owns, one module each: the fixed-point control law (:mod:`firmware_model.control_law`, numba
kernel: the reference model; the same control period in C99 is ``c/ilc_control.c`` with its
interface ``c/ilc_drive.h``, built as the extension ``_fwcore``), which implementation a drive runs
(:mod:`firmware_model.firmware_select`, ``--firmware``; docs/firmware.md), processor in the loop --
the same C on an emulated Cortex-M4, ``c/pil/`` -- (:mod:`firmware_model.pil`, its QEMU link
:mod:`firmware_model.pil_link` and its image build :mod:`firmware_model.pil_build`), the CiA 402
state machine (:mod:`firmware_model.cia402`), the power stage -- torque on/off, quick stop, faults,
communication errors, EMCY, SAFE-STATE records (:mod:`firmware_model.power_stage`) --, the motion
profile generator in fixed point (:mod:`firmware_model.profile`), the operation modes that play
trials -- table playback, CSP, CSV, CST (:mod:`firmware_model.modes`) --, profile position and
homing (:mod:`firmware_model.positioning`), the mode selected, the quick-stop ramp and the homing
offset (:mod:`firmware_model.motion`), trial playback with its tables and data recorder
(:mod:`firmware_model.playback`), the cyclic PDO exchange, its timers and SYNC pacing
(:mod:`firmware_model.cyclic_pdo`), the object-dictionary hooks (:mod:`firmware_model.od_hooks`),
the drive as their composition with its NMT state and its clock (:mod:`firmware_model.drive`, class
``Drive``), the drive process on the bus (:mod:`firmware_model.drive_node`, ``ilcrig drive``), a
trial's plain io ticks run by the C core outside the interpreter (:mod:`firmware_model.plain_ticks`)
and its fieldbus frames waiting in order for the period of the SYNC-stepped robot in progress
(:mod:`firmware_model.sync_backlog`).

May import: ``bus`` and ``bus.cia301`` (the contract it shares with the host).  Never ``host`` or
``plant``: the drive knows the robot only through its encoder and its torque command.
"""
