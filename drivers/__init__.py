"""Device-facing interfaces and adapters. Never imports planners/."""
