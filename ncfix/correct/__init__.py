"""correct stage of ncfix."""
