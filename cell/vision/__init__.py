"""Finding, classifying and locating parts on the backlit table."""
