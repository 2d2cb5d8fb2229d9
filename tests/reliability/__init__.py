"""Bad inputs: every one gets a one-line answer (issue 20)."""
