"""Camera backends: ``genicam://`` (harvesters), ``v4l2://`` (OpenCV), ``replay://`` (a dataset),
``sim://`` (the simulated bench). Pick one with :func:`drivers.acquisition.config.open_camera`."""
