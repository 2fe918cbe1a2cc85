"""Everything that knows a file format: logs, YAML/JSON reports."""
