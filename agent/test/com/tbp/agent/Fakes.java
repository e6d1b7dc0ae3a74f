package com.tbp.agent;

import java.io.Closeable;
import java.io.File;
import java.io.IOException;
import java.nio.ByteBuffer;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.util.ArrayDeque;
import java.util.ArrayList;
import java.util.List;
import java.util.Map;
import java.util.concurrent.atomic.AtomicInteger;

/** Test doubles: a camera whose calls the test answers by hand, a client that records answers, a platform of fakes. */
final class Fakes {

    private Fakes() {
    }

    static final CameraBackend.Info INFO = new CameraBackend.Info("Fake Phone", "FAKE0001", 10.0, 1, "realtime",
            0.002, 50, 64, 48, 1e-5, 0.5, 50, 3200);

    static class Camera implements CameraBackend {
        final ArrayDeque<Result<Focused>> focuses = new ArrayDeque<>();
        final ArrayDeque<Double> focusTargets = new ArrayDeque<>();
        final ArrayDeque<Result<Still>> captures = new ArrayDeque<>();
        final ArrayDeque<double[]> captureSettings = new ArrayDeque<>();
        long clockNs = 81_234_567_890_123L;
        RuntimeException failOnCapture;
        boolean closed;

        @Override
        public Info info() {
            return INFO;
        }

        @Override
        public void focus(double diopters, Result<Focused> result) {
            focusTargets.add(diopters);
            focuses.add(result);
        }

        @Override
        public void capture(double exposureS, long iso, Result<Still> result) {
            if (failOnCapture != null) {
                throw failOnCapture;
            }
            captureSettings.add(new double[] {exposureS, iso});
            captures.add(result);
        }

        @Override
        public void readClock(Result<Long> result) {
            result.ok(clockNs);
        }

        @Override
        public void close() {
            closed = true;
        }

        /** Answers the oldest capture with a JPEG of {@code size} bytes. */
        FakeStill answerCapture(int size) {
            FakeStill still = still(size);
            captures.poll().ok(still);
            return still;
        }
    }

    static FakeStill still(int size) {
        return new FakeStill(size, 1000L + size, 0.002, 2.5);
    }

    static final class FakeStill extends CameraBackend.Still {
        final byte[] bytes;
        int releases;

        FakeStill(int size, long timestampNs, double exposureS, double focus) {
            super(timestampNs, exposureS, focus);
            bytes = new byte[size];
            for (int i = 0; i < size; i++) {
                bytes[i] = (byte) i;
            }
        }

        @Override
        public ByteBuffer jpeg() {
            return ByteBuffer.wrap(bytes);
        }

        @Override
        public void release() {
            releases++;
        }
    }

    static final class Client implements Connection {
        final List<String> lines = new ArrayList<>();
        boolean closed;

        @Override
        public void send(byte[] line) {
            lines.add(new String(line, StandardCharsets.UTF_8));
        }

        @Override
        public void close() {
            closed = true;
        }

        /** The answers so far, parsed, and forgotten. */
        @SuppressWarnings("unchecked")
        List<Map<String, Object>> take() {
            List<Map<String, Object>> out = new ArrayList<>();
            for (String line : lines) {
                if (!line.endsWith("\n") || line.indexOf('\n') != line.length() - 1) {
                    throw new AssertionError("not one line: " + line);
                }
                try {
                    out.add((Map<String, Object>) Json.parse(line));
                } catch (Json.SyntaxError e) {
                    throw new AssertionError("answer is not JSON: " + line, e);
                }
            }
            lines.clear();
            return out;
        }
    }

    static final class Recorder implements Log {
        final List<String> errors = new ArrayList<>();

        @Override
        public void info(String message) {
        }

        @Override
        public void error(String message, Throwable cause) {
            errors.add(message + ": " + cause);
        }
    }

    /** A platform of fakes: the given camera (or the failure the test sets in cameraFailure), an image folder in a
     * temporary directory, a listener that counts its closes. */
    static class FakePlatform implements Platform {
        final CameraBackend camera;
        final AtomicInteger listenerClosed = new AtomicInteger();
        Exception cameraFailure;

        FakePlatform(CameraBackend camera) {
            this.camera = camera;
        }

        @Override
        public Log log() {
            return new Recorder();
        }

        @Override
        public CameraBackend openCamera(double exposureS, long iso) throws Exception {
            if (cameraFailure != null) {
                throw cameraFailure;
            }
            return camera;
        }

        @Override
        public ImageStore imageStore() {
            try {
                return new ImageStore(folder(), new Disk());
            } catch (IOException e) {
                throw new AssertionError(e);
            }
        }

        @Override
        public Closeable listen(String name, Agent agent) {
            return new Closeable() {
                @Override
                public void close() {
                    listenerClosed.incrementAndGet();
                }
            };
        }
    }

    /** Free space the test sets. */
    static final class Disk implements ImageStore.FreeSpace {
        long free = 1L << 40;

        @Override
        public long usableBytes(File folder) {
            return free;
        }
    }

    static File folder() throws IOException {
        File folder = Files.createTempDirectory("tbp-agent-test").toFile();
        folder.deleteOnExit();
        return new File(folder, "tbp");
    }
}
