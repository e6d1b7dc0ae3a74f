package com.tbp;

import com.tbp.agent.Launcher;
import com.tbp.agent.sim.SimPlatform;

/**
 * The capture agent's simulator build: the same agent as on a phone, with the simulated phone's
 * camera in place of Camera2 and its bus in place of the abstract socket ({@link SimPlatform}).
 */
public final class CaptureAgent {

    private CaptureAgent() {
    }

    public static void main(String[] args) {
        int status;
        try {
            SimPlatform platform = SimPlatform.fromEnvironment();
            status = platform == null ? 2 : Launcher.run(args, platform, System.in, System.out);
        } catch (Throwable t) {
            t.printStackTrace();
            status = 1;
        }
        System.exit(status);  // the reader threads are daemons, but say it: the agent is done
    }
}
