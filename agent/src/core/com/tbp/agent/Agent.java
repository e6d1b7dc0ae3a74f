package com.tbp.agent;

import java.util.ArrayDeque;
import java.util.HashMap;
import java.util.Iterator;
import java.util.Map;
import java.util.concurrent.LinkedBlockingQueue;

/**
 * The capture agent's protocol side (docs/capture-agent-protocol.md, version 1), one dispatcher
 * thread over an event queue: bytes from clients, camera results and the end of the shell stream
 * arrive as events from any thread and are handled one at a time, in order, on the thread that
 * calls {@link #run()}. Camera operations (focus, capture) run one at a time in arrival order
 * from a queue of at most {@value #CAMERA_QUEUE_LIMIT}; hello, clock and delete are answered at
 * once, so answers may overtake each other. Nothing a client sends stops the agent: every
 * malformed or refused request gets the protocol's error answer and the next line is read.
 */
public final class Agent {

    public static final int PROTOCOL_VERSION = 1;
    /** Longest line in either direction, '\n' included. */
    public static final int MAX_LINE = 64 * 1024;
    /** Camera operations waiting or running; one more is answered CAMERA_BUSY. */
    public static final int CAMERA_QUEUE_LIMIT = 8;

    private final CameraBackend camera;
    private final CameraBackend.Info info;
    private final ImageStore store;
    private final Log log;
    private final LinkedBlockingQueue<Runnable> events = new LinkedBlockingQueue<>();

    // Dispatcher thread only.
    private final Map<Connection, LineFramer> connections = new HashMap<>();
    private final ArrayDeque<CameraOp> waiting = new ArrayDeque<>();
    private CameraOp running;
    private boolean stopping;

    public Agent(CameraBackend camera, ImageStore store, Log log) {
        this.camera = camera;
        this.info = camera.info();
        this.store = store;
        this.log = log;
    }

    // ------------------------------------------------------------------ events, from any thread

    /** Runs {@code event} on the dispatcher thread after the events already queued. */
    public void post(Runnable event) {
        events.add(event);
    }

    public void opened(final Connection connection) {
        post(new Runnable() {
            @Override
            public void run() {
                if (!stopping) {
                    connections.put(connection, new LineFramer(MAX_LINE));
                }
            }
        });
    }

    /** Bytes a client sent (copied: the caller may reuse {@code data}). */
    public void received(final Connection connection, byte[] data, int offset, int count) {
        final byte[] copy = new byte[count];
        System.arraycopy(data, offset, copy, 0, count);
        post(new Runnable() {
            @Override
            public void run() {
                onBytes(connection, copy);
            }
        });
    }

    /** The client closed its connection (or it failed): its waiting camera operations are dropped. */
    public void closed(final Connection connection) {
        post(new Runnable() {
            @Override
            public void run() {
                onClosed(connection);
            }
        });
    }

    /** The shell stream that started the agent closed: close everything and end {@link #run()}. */
    public void stop() {
        post(new Runnable() {
            @Override
            public void run() {
                stopping = true;
            }
        });
    }

    /** The dispatcher: handles events until {@link #stop()}, then closes the clients and the camera. */
    public void run() throws InterruptedException {
        try {
            while (!stopping) {
                dispatch(events.take());
            }
        } finally {
            shutDown();
        }
    }

    private void dispatch(Runnable event) {
        try {
            event.run();
        } catch (RuntimeException e) {
            log.error("event failed", e);
        }
    }

    void shutDown() {
        for (Connection connection : connections.keySet()) {
            connection.close();
        }
        connections.clear();
        waiting.clear();
        camera.close();
    }

    /** Handles the events queued so far on the calling thread (tests drive the agent this way). */
    void runPending() {
        Runnable event;
        while (!stopping && (event = events.poll()) != null) {
            dispatch(event);
        }
    }

    boolean stopping() {
        return stopping;
    }

    // ------------------------------------------------------------------ dispatcher

    private void onBytes(final Connection connection, byte[] data) {
        LineFramer framer = connections.get(connection);
        if (framer == null) {  // bytes that were on their way as the client closed
            return;
        }
        framer.feed(data, 0, data.length, new LineFramer.Sink() {
            @Override
            public void line(byte[] line) {
                handle(connection, line);
            }

            @Override
            public void overlong(long bytes) {
                send(connection, Answer.error(0, ErrorCode.BAD_REQUEST,
                        "line of " + bytes + " bytes > " + MAX_LINE));
            }
        });
    }

    private void onClosed(Connection connection) {
        if (connections.remove(connection) == null) {
            return;
        }
        connection.close();
        for (Iterator<CameraOp> it = waiting.iterator(); it.hasNext(); ) {
            if (it.next().connection == connection) {
                it.remove();
            }
        }
    }

    private void send(Connection connection, Answer answer) {
        if (connections.containsKey(connection)) {
            connection.send(answer.line());
        }
    }

    private void handle(Connection connection, byte[] line) {
        Request request;
        try {
            request = Request.parse(line);
        } catch (AgentError e) {
            send(connection, Answer.error(0, e));
            return;
        }
        try {
            Answer answer = answer(connection, request);
            if (answer != null) {
                send(connection, answer);
            }
        } catch (AgentError e) {
            send(connection, Answer.error(request.id, e));
        } catch (RuntimeException e) {
            log.error(request.op + " failed", e);
            send(connection, Answer.error(request.id, ErrorCode.CAMERA_ERROR, request.op + ": " + e));
        }
    }

    /** The immediate answer to a request, or null when it is answered later (camera, clock). */
    private Answer answer(Connection connection, Request request) throws AgentError {
        switch (request.op) {
            case "hello":
                return hello(request.id);
            case "clock":
                clock(connection, request.id);
                return null;
            case "delete":
                store.delete(request.text("path"));
                return Answer.ok(request.id);
            case "focus":
                enqueue(CameraOp.focus(connection, request.id, focusTarget(request)));
                return null;
            case "capture":
                enqueue(CameraOp.capture(connection, request.id, exposure(request), iso(request)));
                return null;
            default:
                throw new AgentError(ErrorCode.UNKNOWN_OP, "unknown op " + Json.excerpt(request.op));
        }
    }

    private Answer hello(long id) {
        return Answer.ok(id)
                .put("agent_version", (long) PROTOCOL_VERSION)
                .put("model", info.model)
                .put("serial", info.serial)
                .put("min_focus_diopters", info.minFocusDiopters)
                .put("focus_distance_calibration", (long) info.focusDistanceCalibration)
                .put("timestamp_source", info.timestampSource)
                .put("exposure_s", info.exposureS)
                .put("iso", info.iso)
                .put("image_width", (long) info.imageWidth)
                .put("image_height", (long) info.imageHeight);
    }

    private void clock(final Connection connection, final long id) {
        camera.readClock(new Reply<Long>() {
            @Override
            void done(Long deviceNs) {
                send(connection, Answer.ok(id).put("device_ns", deviceNs));
            }

            @Override
            void refused(ErrorCode code, String message) {
                send(connection, Answer.error(id, code, message));
            }
        });
    }

    private double focusTarget(Request request) throws AgentError {
        double diopters = request.number("diopters");
        if (diopters < 0 || diopters > info.minFocusDiopters) {
            throw new AgentError(ErrorCode.FOCUS_OUT_OF_RANGE,
                    diopters + " D outside [0, " + info.minFocusDiopters + "] D");
        }
        return diopters;
    }

    private double exposure(Request request) throws AgentError {
        if (!request.has("exposure_s")) {
            return info.exposureS;
        }
        return withinSensor("exposure_s", request.number("exposure_s"), info.minExposureS, info.maxExposureS, " s");
    }

    private long iso(Request request) throws AgentError {
        if (!request.has("iso")) {
            return info.iso;
        }
        return withinSensor("iso", request.integer("iso"), info.minIso, info.maxIso, "");
    }

    /** A capture setting the request gives, refused when outside the sensor's [low, high] (unit: after the range). */
    private static <T extends Number> T withinSensor(String key, T value, T low, T high, String unit)
            throws AgentError {
        if (value.doubleValue() < low.doubleValue() || value.doubleValue() > high.doubleValue()) {
            throw new AgentError(ErrorCode.BAD_REQUEST, "capture: " + key + " " + value + " outside the sensor's ["
                    + low + ", " + high + "]" + unit);
        }
        return value;
    }

    // ------------------------------------------------------------------ the camera queue

    private void enqueue(CameraOp op) throws AgentError {
        if (waiting.size() + (running != null ? 1 : 0) >= CAMERA_QUEUE_LIMIT) {
            throw new AgentError(ErrorCode.CAMERA_BUSY, CAMERA_QUEUE_LIMIT + " camera operations already queued");
        }
        waiting.add(op);
        startNext();
    }

    private void startNext() {
        while (running == null && !waiting.isEmpty() && !stopping) {
            CameraOp op = waiting.poll();
            running = op;
            try {
                start(op);
            } catch (RuntimeException e) {
                log.error(op.name() + " failed to start", e);
                running = null;
                send(op.connection, Answer.error(op.id, ErrorCode.CAMERA_ERROR, op.name() + ": " + e));
            }
        }
    }

    private void start(final CameraOp op) {
        if (op.capture) {
            camera.capture(op.exposureS, op.iso, new Reply<CameraBackend.Still>() {
                @Override
                void done(CameraBackend.Still still) {
                    finish(op, stored(op, still));
                }

                @Override
                void refused(ErrorCode code, String message) {
                    finish(op, Answer.error(op.id, code, message));
                }
            });
        } else {
            camera.focus(op.diopters, new Reply<CameraBackend.Focused>() {
                @Override
                void done(CameraBackend.Focused focused) {
                    finish(op, Answer.ok(op.id).put("diopters", focused.diopters).put("lens_state", 0L)
                            .put("stationary_at_ns", focused.stationaryAtNs));
                }

                @Override
                void refused(ErrorCode code, String message) {
                    finish(op, Answer.error(op.id, code, message));
                }
            });
        }
    }

    /** Writes the still, unless its client has gone (then nobody could pull or delete the file). */
    private Answer stored(CameraOp op, CameraBackend.Still still) {
        try {
            if (!connections.containsKey(op.connection)) {
                return null;
            }
            ImageStore.Stored image = store.write(still.jpeg());
            return Answer.ok(op.id).put("sensor_timestamp_ns", still.sensorTimestampNs)
                    .put("exposure_s", still.exposureS).put("focus_diopters", still.focusDiopters)
                    .put("path", image.path).put("size", image.size);
        } catch (AgentError e) {
            return Answer.error(op.id, e);
        } finally {
            still.release();
        }
    }

    private void finish(CameraOp op, Answer answer) {
        if (running == op) {
            running = null;
        }
        if (answer != null) {
            send(op.connection, answer);
        }
        startNext();
    }

    /**
     * A backend's answer, handed to the dispatcher thread; a second answer to the same call, or
     * one after the agent stopped, is logged and dropped (a still's buffer is released).
     */
    private abstract class Reply<T> implements CameraBackend.Result<T> {
        private boolean answered;

        abstract void done(T value);

        abstract void refused(ErrorCode code, String message);

        private synchronized boolean first() {
            if (answered) {
                log.error("camera answered twice", new IllegalStateException("second answer"));
                return false;
            }
            answered = true;
            return true;
        }

        @Override
        public final void ok(final T value) {
            if (!first()) {
                release(value);
                return;
            }
            post(new Runnable() {
                @Override
                public void run() {
                    if (stopping) {
                        release(value);
                    } else {
                        done(value);
                    }
                }
            });
        }

        @Override
        public final void failed(final ErrorCode code, final String message) {
            if (first()) {
                post(new Runnable() {
                    @Override
                    public void run() {
                        if (!stopping) {
                            refused(code, message);
                        }
                    }
                });
            }
        }
    }

    private static void release(Object value) {
        if (value instanceof CameraBackend.Still) {
            ((CameraBackend.Still) value).release();
        }
    }
}
