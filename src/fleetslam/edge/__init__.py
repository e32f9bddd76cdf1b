"""The robot: read frames, run the stages before the offloading point, send, upload keyframes."""
