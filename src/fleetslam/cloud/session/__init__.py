"""One robot's session in the cloud: its inbox and memory budget, tracking, uploads, the end
handshake, its checkpoints and outputs, the table of live sessions, and the store they are
kept in (keyframes and checkpoints on disk)."""
