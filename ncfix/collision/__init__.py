"""collision stage of ncfix."""
