"""Where data enters and leaves through files: recordings, TOML configuration, resources."""
