"""The error raised for robot files (YAML tables and URDF) that cannot be read."""


class RobotFileError(ValueError):
    """A robot file that cannot be read; the message names the file, row and field."""
