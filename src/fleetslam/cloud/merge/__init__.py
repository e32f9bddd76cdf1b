"""The fleet's merge in the cloud: the merger role (one worker at a time), its service that
joins robots' maps as keyframes arrive, the requests that ask for a merge, and the frames
the fleet's map sends back to the robots."""
