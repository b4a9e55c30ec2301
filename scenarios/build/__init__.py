"""The model author's build loop, timed (`symkf bench build`)."""
