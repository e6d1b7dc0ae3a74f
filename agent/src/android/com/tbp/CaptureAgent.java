package com.tbp;

import android.os.Looper;
import android.system.Os;
import com.tbp.agent.Launcher;
import com.tbp.agent.android.AndroidPlatform;
import com.tbp.agent.android.Workarounds;

/**
 * The capture agent on a phone, started by the controller over ADB (docs/capture-agent-protocol.md):
 * {@code CLASSPATH=/data/local/tmp/tbp-capture-agent.jar app_process / com.tbp.CaptureAgent
 * socket=tbp-capture version=1}. It runs as the shell user. The main thread becomes the process's
 * main Looper, as framework code expects of an app, and the agent runs on its own thread; the
 * process ends with the agent (System.exit: the framework's threads would keep it alive).
 */
public final class CaptureAgent {

    /** The shell user, whose package (com.android.shell) the agent's calls are attributed to. */
    static final int SHELL_UID = 2000;

    private CaptureAgent() {
    }

    public static void main(final String[] args) {
        dropRoot();
        try {
            Looper.prepareMainLooper();
        } catch (IllegalStateException alreadyPrepared) {
            // app_process prepared it: use that one
        }
        Workarounds.apply();
        Thread agent = new Thread(new Runnable() {
            @Override
            public void run() {
                int status;
                try {
                    status = Launcher.run(args, new AndroidPlatform(), System.in, System.out);
                } catch (Throwable t) {
                    t.printStackTrace();
                    status = 1;
                }
                System.exit(status);
            }
        }, "tbp-capture-agent");
        agent.start();
        Looper.loop();
    }

    /** After {@code adb root} app_process runs as root, whose calls do not match the shell's package. */
    private static void dropRoot() {
        try {
            if (Os.getuid() == 0) {
                Os.setuid(SHELL_UID);
            }
        } catch (Exception e) {
            System.err.println("tbp-capture-agent: cannot become the shell user: " + e);
        }
    }
}
