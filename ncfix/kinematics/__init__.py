"""kinematics stage of ncfix."""
