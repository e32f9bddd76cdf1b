"""The cloud: one isolated tracking session per robot, keyframe storage, dense maps, merge."""
