"""The online check: drift test and update from a short check, repeatability."""
