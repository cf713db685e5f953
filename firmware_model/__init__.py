"""firmware_model: the servo-drive firmware (fixed-point control loop, CiA 402 state
machine, object dictionary, feed-forward table playback, data recorder).
Never imports :mod:`host` or :mod:`plant`."""
