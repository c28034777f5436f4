"""nc stage of ncfix."""
