package com.tbp.agent;

/** The protocol's error codes (docs/capture-agent-protocol.md, "Error codes"). */
public enum ErrorCode {
    BAD_REQUEST,
    UNKNOWN_OP,
    CAMERA_BUSY,
    CAMERA_ERROR,
    FOCUS_OUT_OF_RANGE,
    FOCUS_TIMEOUT,
    CAPTURE_FAILED,
    STORAGE_FULL,
    NOT_FOUND
}
