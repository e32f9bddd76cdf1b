"""Robot-to-cloud transport: the emulated link on a robot's send path."""
