"""The shared core every swimm service imports: settings, keys, messages, Zenoh sessions."""
