package com.tbp.agent;

import java.io.Closeable;
import java.io.IOException;

/** What the agent needs from the system it runs on: a phone (Camera2), or the JVM beside a simulated phone. */
public interface Platform {

    Log log();

    /**
     * Opens the back main camera, ready to focus and capture.
     *
     * @param exposureS the manual exposure (s) from the command line, 0 for the platform's default
     * @param iso       the sensitivity from the command line, 0 for the platform's default
     * @throws Exception with a message the controller quotes in its AgentStartFailed
     */
    CameraBackend openCamera(double exposureS, long iso) throws Exception;

    /** The image folder ({@value ImageStore#PHONE_FOLDER} on the phone). */
    ImageStore imageStore();

    /** Binds the abstract socket {@code name} and hands its clients to {@code agent} until closed. */
    Closeable listen(String name, Agent agent) throws IOException;
}
