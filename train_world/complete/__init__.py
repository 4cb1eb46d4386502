"""What a trained world adds for what its views did not see (:mod:`.shell`)."""
