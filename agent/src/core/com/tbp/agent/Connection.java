package com.tbp.agent;

/**
 * One client of the agent's socket (the host's {@code localabstract:tbp-capture} stream). The
 * platform reports its bytes and its end to {@link Agent#received} and {@link Agent#closed}.
 */
public interface Connection {

    /** Queue one answer line; never blocks the caller for long. */
    void send(byte[] line);

    /** Close the connection; idempotent. */
    void close();
}
