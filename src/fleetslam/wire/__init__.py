"""Messages between robot and cloud."""
