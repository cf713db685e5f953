"""bus: everything drives and host must agree on (units, fixed-point formats, object
indices, frame layouts), the CANopen subset, the io-channel frames and the transports."""
