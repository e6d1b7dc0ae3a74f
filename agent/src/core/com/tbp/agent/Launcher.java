package com.tbp.agent;

import java.io.Closeable;
import java.io.IOException;
import java.io.InputStream;
import java.io.PrintStream;
import java.util.HashMap;
import java.util.Map;
import java.util.concurrent.atomic.AtomicBoolean;

/**
 * The agent's life, as docs/capture-agent-protocol.md starts it: {@code app_process / com.tbp.CaptureAgent
 * socket=tbp-capture version=1}. Opens the camera and the image folder, binds the socket, prints the
 * READY line, serves until the shell stream that started it closes (its stdin ends), then closes the
 * camera and returns. If closing takes longer than {@value #EXIT_DEADLINE_MS} ms the process halts.
 */
public final class Launcher {

    public static final String READY_PREFIX = "TBP-CAPTURE-AGENT READY";
    public static final long EXIT_DEADLINE_MS = 800;

    private Launcher() {
    }

    /** Runs the agent; the exit status: 0 after the shell stream closed, 1 when it could not start, 2 for bad arguments. */
    public static int run(String[] args, Platform platform, InputStream shell, PrintStream out) throws InterruptedException {
        Map<String, String> options = new HashMap<>();
        for (String arg : args) {
            int eq = arg.indexOf('=');
            if (eq <= 0) {
                out.println("tbp-capture-agent: argument " + arg + " is not KEY=VALUE");
                return 2;
            }
            options.put(arg.substring(0, eq), arg.substring(eq + 1));
        }
        String socket = options.containsKey("socket") ? options.get("socket") : "tbp-capture";
        double exposureS;
        long iso;
        try {
            int version = Integer.parseInt(value(options, "version", "1"));
            if (version != Agent.PROTOCOL_VERSION) {
                out.println("tbp-capture-agent: protocol version " + version + " requested, this agent speaks "
                        + Agent.PROTOCOL_VERSION);
                return 2;
            }
            exposureS = Double.parseDouble(value(options, "exposure_s", "0"));
            iso = Long.parseLong(value(options, "iso", "0"));
        } catch (NumberFormatException e) {
            out.println("tbp-capture-agent: bad number in " + options + ": " + e.getMessage());
            return 2;
        }
        Log log = platform.log();
        CameraBackend camera;
        try {
            camera = platform.openCamera(exposureS, iso);
        } catch (Exception e) {
            out.println("tbp-capture-agent: cannot open the camera: " + e);
            log.error("cannot open the camera", e);
            return 1;
        }
        ImageStore store = platform.imageStore();
        Agent agent = new Agent(camera, store, log);
        Closeable listener;
        try {
            store.open();
            listener = platform.listen(socket, agent);
        } catch (IOException e) {
            out.println("tbp-capture-agent: " + e.getMessage());
            camera.close();
            return 1;
        }
        AtomicBoolean done = new AtomicBoolean();
        watchShell(shell, agent, log, done);
        out.println(READY_PREFIX + " " + socket + " " + Agent.PROTOCOL_VERSION);
        out.flush();
        try {
            agent.run();
        } finally {
            try {
                listener.close();
            } catch (IOException e) {
                log.error("closing the socket", e);
            }
            done.set(true);
        }
        return 0;
    }

    private static String value(Map<String, String> options, String key, String fallback) {
        String value = options.get(key);
        return value != null ? value : fallback;
    }

    /** Stops the agent when the shell stream ends, and halts the process if stopping hangs. */
    private static void watchShell(final InputStream shell, final Agent agent, final Log log, final AtomicBoolean done) {
        Thread watcher = new Thread(new Runnable() {
            @Override
            public void run() {
                byte[] buffer = new byte[256];
                try {
                    int n;
                    do {
                        n = shell.read(buffer);  // the agent reads no commands, only the stream's end
                    } while (n >= 0);
                } catch (IOException e) {
                    log.info("shell stream failed: " + e.getMessage());
                }
                agent.stop();
                try {
                    Thread.sleep(EXIT_DEADLINE_MS);
                } catch (InterruptedException e) {
                    return;
                }
                if (done.get()) {
                    return;
                }
                log.error("still running " + EXIT_DEADLINE_MS + " ms after the shell stream closed: halting",
                        new IllegalStateException("exit deadline"));
                Runtime.getRuntime().halt(3);
            }
        }, "shell-watch");
        watcher.setDaemon(true);
        watcher.start();
    }
}
