package com.tbp.agent.sim;

import com.tbp.agent.Agent;
import com.tbp.agent.CameraBackend;
import com.tbp.agent.Connection;
import com.tbp.agent.ImageStore;
import com.tbp.agent.Log;
import com.tbp.agent.Platform;

import java.io.Closeable;
import java.io.File;
import java.io.IOException;
import java.net.StandardProtocolFamily;
import java.net.UnixDomainSocketAddress;
import java.nio.channels.SocketChannel;
import java.nio.charset.StandardCharsets;
import java.util.HashMap;
import java.util.Map;

/**
 * The agent under the JVM beside a simulated phone (``tbp sim phone --agent-runtime jvm``): the
 * simulator starts it with {@code java} in place of {@code app_process}, with two variables:
 * {@value #BUS_VARIABLE}, the UNIX socket of its {@link SimBus}, and {@value #STORAGE_VARIABLE},
 * the host folder that stands for {@value ImageStore#PHONE_FOLDER}. The agent's socket is a bus
 * channel per host stream; the camera is {@link SimCamera}. One reader thread hands every frame to
 * the agent's dispatcher in order, and a SYNC is acknowledged only after the dispatcher has handled
 * everything before it, which is how the simulator knows the agent is idle (its clock may move).
 */
public final class SimPlatform implements Platform {

    public static final String BUS_VARIABLE = "TBP_SIM_BUS";
    public static final String STORAGE_VARIABLE = "TBP_SIM_STORAGE";

    private final SimBus bus;
    private final File storage;
    private final SimCamera camera;
    private final Map<Integer, Channel> channels = new HashMap<>();
    private volatile Agent agent;

    private final Log log = new Log() {
        @Override
        public void info(String message) {
            System.err.println("tbp-capture-agent: " + message);
        }

        @Override
        public void error(String message, Throwable cause) {
            System.err.println("tbp-capture-agent: " + message + ": " + cause);
        }
    };

    private SimPlatform(SimBus bus, File storage) {
        this.bus = bus;
        this.storage = storage;
        this.camera = new SimCamera(bus);
    }

    /** Connects to the simulator named by the environment; null (with a message on stderr) outside it. */
    public static SimPlatform fromEnvironment() throws IOException {
        String path = System.getenv(BUS_VARIABLE);
        String storage = System.getenv(STORAGE_VARIABLE);
        if (path == null || storage == null) {
            System.err.println("tbp-capture-agent: this is the simulator's build of the capture agent, started by "
                    + "`tbp sim phone --agent-runtime jvm` (" + BUS_VARIABLE + " and " + STORAGE_VARIABLE + " unset)");
            return null;
        }
        SocketChannel socket = SocketChannel.open(StandardProtocolFamily.UNIX);
        socket.connect(UnixDomainSocketAddress.of(path));
        SimPlatform platform = new SimPlatform(new SimBus(socket), new File(storage));
        Thread reader = new Thread(new Runnable() {
            @Override
            public void run() {
                platform.readBus();
            }
        }, "sim-bus");
        reader.setDaemon(true);
        reader.start();
        return platform;
    }

    @Override
    public Log log() {
        return log;
    }

    @Override
    public CameraBackend openCamera(double exposureS, long iso) throws Exception {
        camera.open(exposureS, iso);
        return camera;
    }

    @Override
    public ImageStore imageStore() {
        return new ImageStore(storage, ImageStore.DISK);
    }

    @Override
    public Closeable listen(String name, Agent agent) {
        this.agent = agent;
        bus.write(SimBus.LISTEN, 0, name.getBytes(StandardCharsets.UTF_8));
        return new Closeable() {
            @Override
            public void close() throws IOException {
                bus.close();
            }
        };
    }

    private void readBus() {
        try {
            SimBus.Frame frame;
            while ((frame = bus.read()) != null) {
                handle(frame);
            }
        } catch (IOException | SimBus.SimulatorGone e) {
            log.info("simulator link: " + e.getMessage());
        }
        camera.bye("the simulated phone closed its link");
        Agent running = agent;
        if (running != null) {
            running.stop();
        }
    }

    private void handle(final SimBus.Frame frame) {
        Agent running = agent;
        switch (frame.kind) {
            case SimBus.REPLY:
                camera.replied(frame.channel, frame.payload);
                return;
            case SimBus.SYNC:
                if (running == null) {  // still starting: nothing else runs that could answer first
                    bus.write(SimBus.SYNCED, frame.channel, new byte[0]);
                } else {
                    running.post(new Runnable() {
                        @Override
                        public void run() {
                            bus.write(SimBus.SYNCED, frame.channel, new byte[0]);
                        }
                    });
                }
                return;
            default:
                break;
        }
        if (running == null) {
            log.info("frame " + frame.kind + " before the agent listens: dropped");
            return;
        }
        switch (frame.kind) {
            case SimBus.OPEN: {
                Channel channel = new Channel(frame.channel);
                channels.put(frame.channel, channel);
                running.opened(channel);
                return;
            }
            case SimBus.DATA: {
                Channel channel = channels.get(frame.channel);
                if (channel != null) {
                    running.received(channel, frame.payload, 0, frame.payload.length);
                }
                return;
            }
            case SimBus.CLOSE: {
                Channel channel = channels.remove(frame.channel);
                if (channel != null) {
                    running.closed(channel);
                }
                return;
            }
            default:
                log.info("unknown frame kind " + frame.kind + " from the simulator: dropped");
        }
    }

    /** One host stream to the agent's socket, carried as a bus channel. */
    private final class Channel implements Connection {
        private final int id;
        private boolean closed;

        Channel(int id) {
            this.id = id;
        }

        @Override
        public void send(byte[] line) {
            bus.write(SimBus.SENT, id, line);
        }

        @Override
        public synchronized void close() {
            if (!closed) {
                closed = true;
                bus.write(SimBus.CLOSED, id, new byte[0]);
            }
        }
    }
}
