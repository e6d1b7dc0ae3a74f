package com.tbp.agent;

/** Where the agent reports what no client asked about: logcat on a phone, stderr under the JVM. */
public interface Log {

    void info(String message);

    void error(String message, Throwable cause);
}
