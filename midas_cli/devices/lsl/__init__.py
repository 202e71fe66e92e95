"""Lab Streaming Layer: record any LSL stream as a modality; publish a session's streams as LSL outlets."""
