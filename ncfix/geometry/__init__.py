"""geometry stage of ncfix."""
