"""The acquisition server: one worker process per device -> a bounded queue -> the session writer."""
