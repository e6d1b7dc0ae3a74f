package com.tbp.agent;

/** A request that ends in an error answer: the protocol's code and a message for the operator. */
public final class AgentError extends Exception {

    private static final long serialVersionUID = 1L;

    public final ErrorCode code;

    public AgentError(ErrorCode code, String message) {
        super(message);
        this.code = code;
    }
}
